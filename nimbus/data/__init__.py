"""The scene model shared by every part of Nimbus, and its readers and writers."""

from nimbus.data.camera import Camera
from nimbus.data.scene import Scene, View, llff_test_names

__all__ = ["Camera", "Scene", "View", "llff_test_names"]
