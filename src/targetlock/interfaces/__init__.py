"""Hardware interfaces of the TeleFLEX rig and their simulated counterparts.

* :mod:`.cia402` - CiA 402 drive driver over CANopen (``CanopenDrives``: the rig's ``Drives``).
* :mod:`.sim_cia402` - simulated CiA 402 drives whose motor is the twin's drive model
  (``targetlock sim-rig``).
* :mod:`.canbus` - CAN bus settings and factory, and the loopback UDP CAN transport.
* :mod:`.od402` - CiA 402 / 301 constants, state decoding and the object dictionary.
* :mod:`.natnet` - OptiTrack NatNet client (frames of data, newest-only hand-off).
* :mod:`.sim_natnet` - simulated NatNet server streaming base and tip rigid bodies.
* :mod:`.mocap` - bending angles from the base and tip rigid bodies.
* :mod:`.safety` - ``SafeDrives``: the safety supervisor every command passes through.
* :mod:`.rigfile` - the hardware rig file (``[can]``, ``[natnet]``, ``[safety]``).

Submodules are imported on demand (canopen and sockets are not needed to import the package).
"""
