"""The calibration tests' small rig, importable by name from this folder's tests and its conftest (a test module
importing ``conftest`` gets whichever folder's conftest comes first on the path, which depends on what else runs)."""

from specgpu.rig.camera import CameraParameters
from specgpu.rig.config import RigDescription

DESC = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))  # paper noise, smallest ROI
