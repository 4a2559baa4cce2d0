"""The scene model shared by every part of Nimbus, and its readers and writers.

``load_scene`` / ``write_scene`` import pycolmap only when called, so importing
this package stays light.
"""

from nimbus.data.camera import Camera
from nimbus.data.io import detect_format, load_scene, write_scene, write_scene_into
from nimbus.data.scene import Scene, View, llff_test_names

__all__ = ["Camera", "Scene", "View", "detect_format", "llff_test_names", "load_scene", "write_scene",
           "write_scene_into"]
