"""The Optronic Laboratories OL490 through its vendor's .NET SDK (pythonnet): the SDK calls (:mod:`.sdk`), the
light (:class:`OL490Light`) and a simulated SDK (:class:`SimulatedOL490Sdk`) exposing the same calls, for CI and
dry runs."""

from specgpu.hardware.ol490.light import OL490Light
from specgpu.hardware.ol490.sdk import (
                                        COLUMNS,
                                        DEFAULT_SDK_TYPE,
                                        DOTNET_CALLS,
                                        GREY_BITS,
                                        SLITS,
                                        DotNetSdk,
                                        OL490Sdk,
                                        OL490Unit,
                                        load_dotnet_sdk,
)
from specgpu.hardware.ol490.simulated import SdkException, SimulatedOL490Sdk

__all__ = ["OL490Light", "COLUMNS", "DEFAULT_SDK_TYPE", "DOTNET_CALLS", "GREY_BITS", "SLITS", "DotNetSdk",
           "OL490Sdk", "OL490Unit", "load_dotnet_sdk", "SdkException", "SimulatedOL490Sdk"]
