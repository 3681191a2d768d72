"""``specgpu stream`` on a small twin for a moment, over every output with every sink (the zarr recording with the
raw frames, EXR snapshots of every result, the preview, the view) under each motion mode, with ``--denoise`` and
``--accumulate``; a failing optional sink (EXR snapshots, preview, view) stopped and reported in one line while the
recording keeps every sequence; a source that falls behind the plan's frame rate said with both rates.

The view runs without napari: its results ring (:func:`specgpu.apps.live_view.view_ring`) on the stream, polled
after each result by a :class:`specgpu.apps.live_view.LiveView` of a stand-in viewer."""

from __future__ import annotations

import re
import time
from types import SimpleNamespace

import numpy as np
import pytest
from cli_helpers import calibrated_rig
from click.testing import CliRunner

from specgpu import io
from specgpu.apps.cli import main
from specgpu.apps.cli import stream as stream_cli
from specgpu.apps.live_view import LiveView, view_ring
from specgpu.io.recording import open_recording
from specgpu.pipeline import sinks
from specgpu.pipeline.decoder_outputs import STREAM_OUTPUTS
from specgpu.pipeline.moving_decode import MOTION_OUTPUTS
from specgpu.pipeline.sinks import CallbackSink
from specgpu.rig import twin

HEIGHT, WIDTH = 240, 320

MOTION_MODES = ("global", "affine", "flow")

#: (motion, outputs, extra options): each output alone and all together, then every output with --denoise (the
#: sigmas carried through the filter; with motion: tests/pipeline/test_denoised_sigma_paths.py), what --accumulate
#: accepts and a half-precision cube, then every motion mode with every output it accepts together, and each of
#: those outputs alone under one mode (in turn): every (mode, output) pair and every output alone on the motion
#: path, without the grid of each mode times each output alone, whose cells add no pair
CASES = ([("none", (name,), ()) for name in STREAM_OUTPUTS] + [("none", STREAM_OUTPUTS, ())]
         + [("none", STREAM_OUTPUTS, ("--denoise",)),
            ("none", ("coefficients", "cube", "XYZ", "sigma"), ("--accumulate", "3")),
            ("none", ("cube", "sigma_rms"), ("--accumulate", "3")), ("none", ("cube", "XYZ"), ("--half",))]
         + [(mode, MOTION_OUTPUTS, ()) for mode in MOTION_MODES]
         + [(MOTION_MODES[i % len(MOTION_MODES)], (name,), ()) for i, name in enumerate(MOTION_OUTPUTS)]
         + [("global", ("cube", "XYZ", "sigma_rms"), ("--accumulate", "3"))])


#: --seconds of the streams here: each ends with its twin's frames (:func:`twin_sequences`) long before; this only
#: bounds it (and sizes the recording's free-space check: keep it small)
BOUND_S = 5


def cli(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def twin_sequences(monkeypatch, sequences: int):
    """The twin driver ``specgpu stream`` opens delivers the frames of ``sequences`` sequences, then its stream ends
    (``TwinDriver.n_frames``), and the stream with it: each stream here decodes exactly that many, whatever the
    machine's load, instead of what a fixed time captures (two or three, every one decoded, written and read back
    again)."""
    opened = stream_cli.open_rig_driver

    def limited(description, plan, **kwargs):
        driver = opened(description, plan, **kwargs)
        driver.n_frames = sequences * plan.K
        return driver

    monkeypatch.setattr(stream_cli, "open_rig_driver", limited)


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """A 320 x 240 twin, its calibration (the session's) and a symmetric plan made through the CLI."""
    d = calibrated_rig(tmp_path_factory.mktemp("sweep"))  # the 320 x 240 twin (HEIGHT, WIDTH)
    result = cli("plan", "symmetric", "--calib", d / "calib.npz", "--rig", d / "rig.toml", "--out", d / "plan.npz")
    assert result.exit_code == 0, result.output
    return d


class FakeViewer:
    """What LiveView uses of a napari viewer: layers added by ``add_image`` and a text overlay."""

    def __init__(self):
        self.text_overlay = SimpleNamespace(text="")
        self.layers = {}

    def add_image(self, data, name, **kwargs):
        self.layers[name] = SimpleNamespace(data=data, **kwargs)
        return self.layers[name]


class View:
    """``run_with_view`` without napari: the view's ring on the stream, and a LiveView of a stand-in viewer that
    polls it after each result (on the sink thread, so it shows every result)."""

    def __init__(self):
        self.views = []

    def __call__(self, stream, seconds, *, wavelengths=None, illuminant="D65", on_sink_stopped=None):
        ring = view_ring()
        view = LiveView(FakeViewer(), stream, ring, wavelengths=wavelengths, illuminant=illuminant)
        stream.sinks += [ring, CallbackSink(lambda result: view.poll())]
        self.views.append(view)
        return stream.run(seconds, on_sink_stopped=on_sink_stopped)


def stream(rig, out, outputs, *extra, motion="none"):
    return cli("stream", "--rig", rig / "rig.toml", "--plan", rig / "plan.npz", "--calib", rig / "calib.npz",
               "--seconds", BOUND_S, "--out", out, "--frames", "--exr-every", 1, "--view", "--no-disk-check",
               "--outputs", ",".join(outputs), "--motion", motion, *extra)


def sequences_out(output: str) -> int:
    return int(re.search(r"(\d+) sequences out \(", output).group(1))


@pytest.mark.parametrize("motion, outputs, extra", CASES,
                         ids=[f"{m}-{'+'.join(o) if len(o) < 3 else len(o)}{''.join(e[:1])}" for m, o, e in CASES])
def test_every_output_reaches_every_sink(rig, tmp_path, monkeypatch, motion, outputs, extra):
    """One sequence streamed with every sink: each output recorded, in its EXR snapshot, previewed and viewed."""
    view = View()
    monkeypatch.setattr(stream_cli, "run_with_view", view)
    twin_sequences(monkeypatch, 1)
    out = tmp_path / "rec.zarr"
    result = stream(rig, out, outputs, *extra, motion=motion)
    assert result.exit_code == 0, result.output
    assert "Warning" not in result.output and "stopped" not in result.output, result.output
    rec = open_recording(out)
    n = rec.sequences
    assert n == sequences_out(result.output) == 1 and rec.attrs["status"] == "complete"
    assert set(rec.attrs["outputs"]) == set(outputs) and rec.read("frames", slice(None)).shape[0] == n
    for name in outputs:
        recorded = rec.read(name, slice(None))
        assert recorded.shape[:3] == (n, HEIGHT, WIDTH) and np.isfinite(recorded).any(), name
        snapshots = sorted(int(p.stem.rsplit("-", 1)[1]) for p in (out / "exr").glob(f"{name}-*.exr"))
        assert snapshots == list(range(n)), (name, snapshots)
        for i in snapshots:  # each snapshot holds the recorded map, each channel of it
            path = out / "exr" / f"{name}-{i:06d}.exr"
            data = io.read_cube(path)[0] if name == "cube" else io.read_map(path)[0]
            np.testing.assert_array_equal(data, recorded[i].reshape(HEIGHT, WIDTH, -1), err_msg=name)
    assert (out / "preview.png").is_file() == ("XYZ" in outputs)
    assert view.views[0].shown == n


def test_the_accumulated_sigma_is_recorded_and_true(rig, tmp_path, monkeypatch):
    """``--accumulate 3`` on a still scene, twice with other noise: the recorded sigma_rms of the k-th sequence is
    one sequence's times sqrt(v), v the running mean's variance factor (1 / (k + 1) up to 3 sequences, then that
    of a recursive mean of weight 1 / 3), and it is the running estimates' own: the two estimates differ by what
    their recorded sigmas say (z-scores of RMS 1). Four sequences: the running mean up to 3, then the recursive one.
    The recording alone is asked for: the other sinks are the sweep's concern."""
    twin_sequences(monkeypatch, 4)
    recorded = []
    for seed in (1, 2):
        out = tmp_path / f"rec{seed}.zarr"
        result = cli("stream", "--rig", rig / "rig.toml", "--plan", rig / "plan.npz", "--calib", rig / "calib.npz",
                     "--seconds", BOUND_S, "--out", out, "--no-disk-check", "--outputs", "cube,sigma_rms",
                     "--accumulate", 3, "--seed", seed, "--pacing", "free")
        assert result.exit_code == 0, result.output
        rec = open_recording(out)
        recorded.append((rec.read("cube", slice(None)), rec.read("sigma_rms", slice(None))))
    n = min(cube.shape[0] for cube, _ in recorded)
    assert n == 4
    for cube, sigma in recorded:
        single, v = np.nanmedian(sigma[0]), 1.0
        for k in range(1, n):
            w = 1.0 / min(k + 1, 3)
            v = (1.0 - w) ** 2 * v + w * w
            assert np.nanmedian(sigma[k]) == pytest.approx(single * np.sqrt(v), rel=0.05), k
    (a, sa), (b, sb) = recorded
    for k in range(1, n):
        ms = np.mean((a[k] - b[k]) ** 2, axis=-1)  # the squared difference over the bands
        s2 = sa[k] ** 2 + sb[k] ** 2
        ok = np.isfinite(ms) & np.isfinite(s2)
        assert 0.9 < np.sqrt(np.mean(ms[ok]) / np.mean(s2[ok])) < 1.12, k


def fail(calls):
    def failing(*args, **kwargs):
        calls.append(1)
        raise OSError(28, "No space left on device")
    return failing


@pytest.mark.parametrize("sink", ["EXR snapshots", "preview", "view"])
def test_a_failing_optional_sink_is_stopped_and_the_recording_keeps_every_sequence(rig, tmp_path, monkeypatch,
                                                                                     sink):
    calls = []
    monkeypatch.setattr(stream_cli, "run_with_view", View())
    if sink == "EXR snapshots":
        monkeypatch.setattr(sinks.io, "write_map", fail(calls))
    elif sink == "preview":
        monkeypatch.setattr(sinks, "write_png", fail(calls))
    else:  # the view's ring copies each result it keeps
        monkeypatch.setattr(sinks, "StreamResult", fail(calls))
    twin_sequences(monkeypatch, 3)
    out = tmp_path / "rec.zarr"
    result = stream(rig, out, ("XYZ", "dE"))
    assert result.exit_code == 0, result.output
    assert calls  # the fault was met
    warnings = [line for line in result.output.splitlines() if "Warning" in line]
    assert len(warnings) == 1, result.output
    assert re.fullmatch(rf"Warning: {sink} stopped( closing)?: OSError: \[Errno 28\] No space left on device; "
                        "the stream goes on", warnings[0]), warnings[0]
    rec = open_recording(out)
    n = sequences_out(result.output)
    assert rec.attrs["status"] == "complete" and rec.sequences == n == 3  # every sequence kept
    summary = result.output.strip().splitlines()[-1]
    assert f"; {sink} stopped" in summary and f"wrote {out} ({n} sequences)" in summary
    if sink == "EXR snapshots":  # the first map failed: no snapshot after it
        assert not list((out / "exr").glob("*-000001.exr"))


def test_a_source_behind_the_plan_says_so_with_both_rates(rig, tmp_path, monkeypatch):
    """The twin renders each frame 30 ms late (a machine too slow for the plan's 90 frames/s): nothing is dropped,
    and the status line and the summary say the frames came at about 30/s, the plan's rate being 90/s."""
    render = twin.TwinRig.render

    def slow(self, *args, **kwargs):
        time.sleep(0.03)
        return render(self, *args, **kwargs)

    monkeypatch.setattr(twin.TwinRig, "render", slow)
    result = cli("stream", "--rig", rig / "rig.toml", "--plan", rig / "plan.npz", "--calib", rig / "calib.npz",
                 "--seconds", 1.2, "--outputs", "XYZ")
    assert result.exit_code == 0, result.output
    lines = result.output.strip().splitlines()
    pattern = r"behind the plan: frames delivered at (\d+)/s, the plan's rate is 90/s"
    status = [re.search(pattern, line) for line in lines[:-1]]
    assert any(status), result.output
    summary = re.search(pattern, lines[-1])
    assert summary and 5 <= int(summary.group(1)) <= 40, lines[-1]
    assert "dropped 0" in lines[-1]
