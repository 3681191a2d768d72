"""`specgpu calibrate` on a rig TOML with a [hardware] table: the procedure runs on the devices it names."""

from __future__ import annotations

from hw_fakes import TwinCamera, TwinSeaBreeze, hardware_table, spectrometer_cal

from specgpu.hardware.dlpc900 import SimulatedDLPC900
from specgpu.planning import make_plan


def test_cli_calibrate_takes_the_hardware_path(tmp_path, monkeypatch):
    """`specgpu calibrate --rig RIG.toml` with a [hardware] table runs the procedure on the devices it names (here
    the simulated controller, with the fake camera and spectrometer put in where the real ones would be opened)."""
    from click.testing import CliRunner

    import specgpu.hardware.rig as hw_rig
    from specgpu.apps.cli import main
    from specgpu.calibration.bundle import load_calibration
    from specgpu.rig.config import load_rig

    real = hw_rig.open_calibration_rig
    opened = []

    def with_fakes(description, *, hardware):
        sim = SimulatedDLPC900(hardware.dmd)
        opened.append(real(description, hardware=hardware, acquirer=TwinCamera(sim, description), transport=sim,
                           spectrometer=TwinSeaBreeze(sim, description, cal=spectrometer_cal())))
        return opened[-1]

    monkeypatch.setattr(hw_rig, "open_calibration_rig", with_fakes)
    table = hardware_table(tmp_path)
    rig_toml = tmp_path / "rig.toml"
    rig_toml.write_text("[camera]\nroi_width = 320\nroi_height = 240\n[hardware]\n"
                        + "".join(f"{k} = {v!r}\n".replace("'", '"') for k, v in table.items()))
    result = CliRunner().invoke(main, ["calibrate", "--rig", str(rig_toml), "--out", str(tmp_path / "c.npz")])
    assert result.exit_code == 0, result.output
    assert "loop (a) camera + white" in result.output and "converged True" in result.output
    assert len(opened) == 1 and opened[0].spectroradiometer.device.closed  # devices released
    bundle = load_calibration(tmp_path / "c.npz", rig=load_rig(rig_toml))
    assert bundle.reports["loop_a"]["converged"] and make_plan("reciprocal", bundle).calibration == bundle.hash
