"""Every command runs BLAS on one thread unless the environment chose a thread count."""


def test_every_command_runs_with_one_blas_thread(monkeypatch):
    from click.testing import CliRunner

    from specgpu.apps.cli import main, options

    calls = []
    monkeypatch.setattr(options, "one_blas_thread", lambda: calls.append(1))
    result = CliRunner().invoke(main, ["bound", "--frames", "3", "--sequence-ms", "50", "--help"])
    assert result.exit_code == 0 and calls == []  # a command's help loads nothing
    result = CliRunner().invoke(main, ["info"])
    assert result.exit_code == 0, result.output
    assert calls == [1]
