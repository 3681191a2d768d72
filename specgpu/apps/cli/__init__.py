"""The ``specgpu`` command.

Every command has --help, exits 0 on success and, on failure, prints one line saying why and exits non-zero.
Each command group lives in its own module of this package, imported only when the command runs (or shows its
help): ``specgpu --help`` lists the commands from :data:`COMMANDS` without loading any.
"""

from __future__ import annotations

import click

from specgpu import __version__
from specgpu.apps.cli.group import LazyGroup

#: Each command: ``(module:attribute, summary)``; the summary is the first paragraph of the command's help (a
#: test keeps them equal).
COMMANDS = {
    "batch": ("specgpu.apps.cli.batch:batch_command",
              ("Re-process the raw frames of a recording (specgpu stream --frames) or a sequence folder with a plan, "
               "on Dask: one task per sequence, resumable, equal to specgpu recover of each sequence.")),
    "bench": ("specgpu.apps.cli.bench:bench",
              "Throughput of each kernel against NumPy / colour-science baselines measured in the same run."),
    "bound": ("specgpu.apps.cli.bound:bound",
              ("The lowest expected per-pixel RMSE any K-frame linear design can reach on the rig within a sequence "
               "time (shot and read noise, the training prior), beside the best design found: the limit lies "
               "between the two.")),
    "calibrate": ("specgpu.apps.cli.calibrate:calibrate",
                  "Run both feedback loops on the rig and write the calibration bundle."),
    "capture": ("specgpu.apps.cli.capture:capture",
                "Capture sequences of a plan on the rig (the twin by default) into a sequence folder."),
    "demo": ("specgpu.apps.cli.demo:demo",
             ("The main job on the built-in twin: calibrate, plan, capture the chart, recover, evaluate; prints the "
              "paper's Tables 1-3 beside ours and writes a report folder with index.html.")),
    "evaluate": ("specgpu.apps.cli.evaluate:evaluate",
                 ("Accuracy of a recovered cube (.exr, .npz or ENVI .hdr; or an XYZ map) against the true scene: per "
                  "pixel, and per patch for a chart, with the pixels left out counted by cause.")),
    "info": ("specgpu.apps.cli.info:info",
             ("OpenCL platforms and devices, the one chosen, and versions; --devices: the OpenCL devices alone; "
              "--usb: the USB devices too.")),
    "plan": ("specgpu.apps.cli.plan:plan_command",
             "Design a measurement plan: the illuminant sequence and its decoder."),
    "recover": ("specgpu.apps.cli.recover:recover",
                ("Recover a sequence folder: the cube and, when asked, XYZ, Lab and dE maps (written only if all "
                 "succeed).")),
    "report": ("specgpu.apps.cli.report:report",
               ("Write the HTML report of a run folder (a capture folder, or folders of captures as the demo writes "
                "them): each capture recovered, scored against its truth, with tables, spectra, error maps and "
                "renderings.")),
    "salvage": ("specgpu.apps.cli.capture:salvage",
                ("Index the complete sequences of a capture folder whose capture was killed (kill -9, a crash, power "
                 "loss).")),
    "selftest": ("specgpu.apps.cli.info:selftest",
                 ("Run the kernel regression suite (golden set) on this machine's device; exit 1 if any kernel "
                  "fails.")),
    "stream": ("specgpu.apps.cli.stream:stream_command",
               ("Stream a plan's sequences from the rig through the device to maps, with a live status line; Ctrl-C "
                "stops cleanly (everything captured is processed or reported).")),
    "view": ("specgpu.apps.cli.view:view",
             ("Open a cube or map (.exr, .npz, ENVI .hdr), a sequence folder or a zarr recording in napari, with the "
              "spectrum widget (needs the viewer extra: pip install 'specgpu[viewer]').")),
}

__all__ = ["COMMANDS", "main"]


@click.group(cls=LazyGroup, lazy_commands=COMMANDS, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="specgpu")
def main():
    """specgpu: active-illumination spectral imaging on OpenCL (Tominaga and Horiuchi, JOSA A 2012)."""


if __name__ == "__main__":  # pragma: no cover
    main()
