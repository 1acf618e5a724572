"""PanoWorld: one indoor 360° panorama to a roamable 3D Gaussian scene."""

__version__ = "0.1.0"
