"""targetlock: keep a flexible endoscope's camera locked on a selected target.

Layout (design notes §1): ``model`` (physics of the endoscope, drives, camera, scene),
``rig`` (what the loop talks to: simulated twin or hardware), ``loop`` (fixed-rate control loop
and clocks), ``controllers`` (PI, PI + hysteresis compensation, inverse kinematics),
``vision`` (renderer and trackers), ``experiments`` (the report's procedures, run folders) and
``interfaces`` (CANopen drives, NatNet motion capture).
"""
__version__ = "0.1.0"
