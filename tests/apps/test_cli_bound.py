"""`specgpu bound`: the limit of any K-frame design printed beside the best design found; bad options refused in one
line."""

from cli_helpers import one_line_error, run


def test_cli_bound_prints_and_refuses(tmp_path):
    rig = tmp_path / "rig.toml"
    rig.write_text("[camera]\nroi_width = 320\nroi_height = 240\n")
    out = run("bound", "--frames", "3", "--sequence-ms", "30", "--starts", "1", "--rig", rig).output
    assert "lower bound" in out and "best design found" in out
    lower = float(out.split("RMSE >= ")[1].split()[0])
    best = float(out.split("RMSE ")[2].split()[0])
    assert 0 < lower <= best
    one_line_error(run("bound", "--frames", "9", "--sequence-ms", "5", "--rig", rig, ok=False), "cannot hold 9 frames")
