"""Vision: the twin's endoscope renderer, target trackers, frame sources, evaluation, overlays.

Typical use on the twin::

    from targetlock.vision import Renderer, RenderSettings, endoscope_camera, FeatureTracker

    renderer = Renderer(endoscope_camera())            # procedural mucosa, distorted camera
    frame = renderer.render(camera_pose, target_pose)  # Frame(image, truth_px, visible, ...)
    tracker = FeatureTracker()
    tracker.select(frame.image, frame.truth_px, window_px=80)
    result = tracker.update(next_frame.image)          # TrackResult(position_px, confidence, valid, lost)

See ``docs/vision.md`` for the models, the evaluation and the numbers reached.
"""
from .evaluate import SEQUENCES, EvalSettings, evaluate, render_sequence, score
from .overlay import draw_overlay
from .render import (Frame, PlanarTarget, Renderer, RenderSettings, endoscope_camera, interpolate_pose,
                     make_pose)
from .sources import CaptureSource, FrameSource, RenderedSource, VideoFileSource, write_video
from .reference import make_reference, reference_trackers
from .texture import PHOTOS, add_dot, aruco_texture, mucosa_texture, photo_texture
from .tracker import (FeatureTracker, MarkerSettings, MarkerTracker, Tracker, TrackerSettings, TrackResult,
                      make_tracker, to_observation)

__all__ = [
    "Renderer", "RenderSettings", "PlanarTarget", "Frame", "endoscope_camera", "make_pose", "interpolate_pose",
    "mucosa_texture", "aruco_texture", "add_dot", "photo_texture", "PHOTOS", "reference_trackers", "make_reference",
    "Tracker", "TrackResult", "FeatureTracker", "TrackerSettings", "MarkerTracker", "MarkerSettings",
    "make_tracker", "to_observation",
    "FrameSource", "RenderedSource", "VideoFileSource", "CaptureSource", "write_video",
    "EvalSettings", "SEQUENCES", "evaluate", "render_sequence", "score",
    "draw_overlay",
]
