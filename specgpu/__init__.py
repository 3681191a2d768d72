"""specgpu: active-illumination spectral imaging on OpenCL.

Frames lit by a programmed sequence of spectra are turned, per pixel, into spectral reflectance,
CIE XYZ, CIELAB and colour-difference maps (Tominaga and Horiuchi, JOSA A 29(9), 2012).
"""

__version__ = "0.1.0"
