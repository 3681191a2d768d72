"""``specgpu calibrate``: both feedback loops on the rig, written as a calibration bundle."""

from __future__ import annotations

import click

from specgpu.apps.cli.options import RIG, Busy, command, lock, no_clash
from specgpu.calibration.bundle import save_calibration
from specgpu.calibration.on_rig import calibrate_on_rig
from specgpu.hardware.drivers import hardware_config
from specgpu.rig.config import load_rig


def loop_lines(reports):
    """One line per feedback loop that ran: iterations, residual, tolerance, converged."""
    return [f"{what}: {r['iterations']} iterations, residual {r['residual']:.4f} (tolerance {r['tolerance']:g}), "
            f"converged {r['converged']}"
            for loop, what in (("loop_a", "loop (a) camera + white"), ("loop_b", "loop (b) spectroradiometer"))
            if (r := reports.get(loop)) is not None]


@command()
@RIG
@click.option("--out", required=True, type=click.Path(dir_okay=False), help="Calibration bundle to write (.npz).")
@click.option("--seed", type=click.IntRange(min=0, max=2**63 - 1), default=0, show_default=True,
              help="Seed of the twin's noise; on hardware, of the loops' perturbed start only.")
@click.option("--line-shape", type=click.Choice(["gaussian", "measured"]), default="gaussian", show_default=True,
              help="The light's line shape in the bundle: the design Gaussian, or tabulated per column from the "
                   "spectroradiometer's probe readings (no model of the slit).")
def calibrate(rig_path, out, seed, line_shape):
    """Run both feedback loops on the rig and write the calibration bundle."""
    no_clash([("--out", out)], [("--rig", rig_path)])
    description = load_rig(rig_path)
    hardware = hardware_config(description)
    lock(out)
    with Busy("calibrating"):
        bundle = calibrate_on_rig(description, hardware=hardware, seed=seed, line_shape=line_shape)
    digest = save_calibration(out, bundle)
    for line in loop_lines(bundle.reports):
        click.echo(line)
    click.echo(f"wrote {out} (calibration {digest[:12]})")
