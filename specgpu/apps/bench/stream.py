"""The stream at camera speed on this machine (``specgpu bench --stream``): frames in per second, sequences out,
latency, drops, CPU and peak RSS on a replayed twin recording, every case checked for exactness against the
offline path."""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from specgpu.core.validate import BadArgument
from specgpu.engine.runtime import get_queue
from specgpu.pipeline.denoise import DENOISE_EPS, DENOISE_RADIUS
from specgpu.pipeline.sequence_decoder import SequenceDecoder
from specgpu.pipeline.stream import Stream
from specgpu.pipeline.stream_report import current_rss_bytes
from specgpu.pipeline.twin_replay import StreamSetup, offline_maps, stream_setup
from specgpu.planning import NoiseModel, smooth_prior, with_estimator
from specgpu.rig.scene import white_tile_roi

__all__ = ["STREAM_CASES", "STREAM_TARGETS", "Checker", "MemoryRecorder", "format_stream_report", "max_rel",
           "run_stream_bench", "stream_targets"]
# ------------------------------------------------------------------------------------------------------ the stream

#: The stream's targets, raw frames per second into the stream, at the paper's 640 x 480 (other sizes print their
#: rates without a verdict).
STREAM_TARGETS = {"coefficients_XYZ_dE2000_fps": 780.0, "cube_float16_fps": 200.0}


def stream_targets(width: int, height: int) -> dict:
    """The targets a stream bench of ``width`` x ``height`` frames is judged by: :data:`STREAM_TARGETS` at
    640 x 480, none at another size (its rate is printed without PASS or MISS)."""
    return dict(STREAM_TARGETS) if (int(width), int(height)) == (640, 480) else {}



def _stream_row(case: str, report, *, target_fps=None, extra=None) -> dict:
    row = {"case": case, **report.as_dict()}
    if target_fps is not None:
        row["target_fps"] = target_fps
        row["passed"] = report.frames_per_s >= target_fps
    row.update(extra or {})
    return row


#: The stream bench's cases; the sustained ones (free-running, ``block``) run ``rounds`` times interleaved.
STREAM_CASES = ("fused", "sigma", "sigma_rms", "white", "dE_sigma", "linear", "denoise", "motion", "motion_flow",
                "static", "full", "paced_full", "cube", "paced", "overload", "equality")
#: The outputs of the static and full cases (and paced_full) where the stream's decoder does not take sigma_rms with
#: ``--motion global --denoise --white-roi`` (:func:`quality_outputs`): full and static compare the same outputs
_QUALITY_OUTPUTS = ("coefficients", "XYZ", "dE")
#: What the full-quality comparison adds where the decoder carries it through the filter
_QUALITY_SIGMA = "sigma_rms"
#: full / static, the least share of the static rate that full quality (motion, denoising, white) may cost
FULL_RATIO_TARGET = 0.40
_SUSTAINED = {"fused": ("coefficients+XYZ+dE2000", ("coefficients", "XYZ", "dE"), False),
              "sigma": ("coefficients+XYZ+dE2000+sigma", ("coefficients", "XYZ", "dE", "sigma"), False),
              "sigma_rms": ("coefficients+XYZ+dE2000+sigma_rms", ("coefficients", "XYZ", "dE", "sigma_rms"), False),
              "white": ("coefficients+XYZ+dE2000 with --white-roi", ("coefficients", "XYZ", "dE"), True),
              "dE_sigma": ("coefficients+XYZ+dE2000+dE_sigma", ("coefficients", "XYZ", "dE", "dE_sigma"), False),
              "linear": ("coefficients+XYZ", ("coefficients", "XYZ"), False),
              "denoise": ("coefficients+XYZ with --denoise", ("coefficients", "XYZ"), False),
              "motion": ("coefficients+XYZ with --motion global", ("coefficients", "XYZ"), False),
              "motion_flow": ("coefficients+XYZ with --motion flow", ("coefficients", "XYZ"), False),
              "static": ("static: coefficients+XYZ+dE2000", _QUALITY_OUTPUTS, False),
              "full": ("full: coefficients+XYZ+dE2000 with --motion global --denoise --white-roi",
                       _QUALITY_OUTPUTS, True)}
#: The options of the full case, as its row names them
_FULL_OPTIONS = " with --motion global --denoise --white-roi"
#: The motion mode of each case that compensates one
_MOTION = {"motion": "global", "motion_flow": "flow", "full": "global"}
#: The cases run with the guided filter
_DENOISED = ("denoise", "full")


def run_stream_bench(*, seconds: float = 10.0, paced_seconds: float = 60.0, overload_seconds: float = 10.0,
                     width: int = 640, height: int = 480, device=None, json_path=None, echo=print,
                     cases=("fused", "sigma", "sigma_rms", "white", "cube", "paced", "overload", "equality"),
                     rounds: int = 1, progress: bool = True) -> dict:
    """The stream at camera speed on this machine, each case checked for exactness; with ``progress``, a line on
    stderr as each step of the set-up (about a minute at 640 x 480) and each case starts.

    Frames are replayed from a recording of the twin (:class:`~specgpu.capture.replay.ReplayDriver`): the twin
    renders fresh noise at ~700 frames/s on 2 cores, slower than the pipeline, so it could not outrun it.

    Cases
    -----
    fused
        Coefficients (m = 5) + XYZ + dE2000 against the scene's per-pixel Lab, replay free-running with the
        ``block`` ring policy (the rate is the pipeline's own), ``seconds`` long. Target 780 frames/s.
    sigma
        The same plus ``sigma`` (each of the 61 outputs' standard deviation and their RMS, float32; the plan
        given the camera's noise model and its expected error on a smooth prior). Target 780 frames/s.
    sigma_rms
        The same with the RMS of the outputs' standard deviations only (one channel). Target 780 frames/s.
    white
        Fused with ``white_roi`` on the white tile above the chart (each sequence's decoder corrected on the
        host and written to the device). Target 780 frames/s.
    dE_sigma
        Fused plus ``dE_sigma`` (XYZ covariance on the device, its dE2000 propagation on the host); no target,
        not run by default.
    linear, denoise
        Coefficients + XYZ, plain and with ``stream --denoise`` (the guided filter of both, its guide the
        frames' sum): the denoiser's cost at equal outputs; no target, not run by default.
    motion
        Coefficients + XYZ with ``stream --motion global`` (each sequence's displacements estimated on the host,
        its frames decoded through the warped kernel), beside ``linear`` (run with it, interleaved) and their
        ratio, with the host seconds per sequence of each step (estimate, warped pass, consistency check,
        colour); the replayed chart is still, so this is the compensation's cost, not its accuracy. Not run by
        default.
    motion_flow
        Coefficients + XYZ with ``stream --motion flow`` (the global decoding, then the tiles' flow, its warped
        pass and its own consistency check, every sequence): the dense mode's rate; no target, not run by default.
    static, full
        Coefficients + XYZ + dE2000, plain (``static``) and with every quality option at once
        (``full``: ``--motion global --denoise --white-roi``, the white tile above the chart), interleaved, and
        the ratio full / static (the median of the rounds' ratios) against :data:`FULL_RATIO_TARGET`. Not run
        by default.
    paced_full
        The full case at the camera's 200 fps (replay paced by the recorded timestamps, ``drop_newest``),
        ``paced_seconds`` long: zero drops required, the latency stated. Not run by default.

    The sustained cases (fused, sigma, white, dE_sigma) run ``rounds`` times interleaved; each row is the
    median round's, with every round's frames/s and 1-minute load average beside it.
    cube
        The 61-band float16 cube, every one copied into an in-memory recording. Target 200 frames/s.
    paced
        Coefficients + XYZ + dE2000 at the camera's 200 fps (replay paced by the recorded timestamps), the
        ``drop_newest`` policy, ``paced_seconds`` long: zero drops and zero misaligned sequences required.
    overload
        The float32 cube + XYZ + dE2000 with the replay free-running into a ``drop_newest`` ring for
        ``overload_seconds``: every drop counted (ring refusals = id gaps, frames in = ids exposed), every result
        checked against the offline maps of the sequence its ids name, peak RSS stated.
    equality
        Stream results (float32 cube, XYZ, Lab, dE2000) against ``pipeline.recover`` on the same frames.
    """
    unknown = set(cases) - set(STREAM_CASES)
    if unknown:
        raise BadArgument(f"unknown stream bench case(s) {sorted(unknown)}; valid: {', '.join(STREAM_CASES)}")
    if int(rounds) < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds}")
    echo = echo or (lambda _s: None)
    say = _stderr_line if progress else (lambda _s: None)
    t_setup = time.perf_counter()
    setup = stream_setup(width, height, white_tile=0.99, progress=say)
    quality = {"static", "full", "paced_full"} & set(cases)
    if {"sigma", "sigma_rms", "dE_sigma"} & set(cases) or quality:
        say("the decoder's noise model and its expected error on a smooth prior (the sigma cases)")
        plan = with_estimator(setup.plan, setup.bundle, "projection", noise=NoiseModel.from_rig(
            setup.description, setup.plan.exposure_s), prior=smooth_prior(np.arange(400.0, 700.0 + 1e-9, 5.0)))
        setup = replace(setup, plan=plan)  # the decoder is unchanged: only its noise model and expected error
    full_outputs = quality_outputs(setup) if quality else _QUALITY_OUTPUTS
    cases_run = {**_SUSTAINED, **{c: (f"{c}: {'+'.join(full_outputs).replace('dE', 'dE2000')}" + rest, full_outputs,
                                      white) for c, rest, white in (("static", "", False),
                                                                    ("full", _FULL_OPTIONS, True))}}
    R = setup.frames.shape[0] // setup.plan.K
    say(f"the offline maps of the {R} recorded sequences (what every streamed result is checked against)")
    # the checkers need XYZ and dE only: the 61-band float32 cubes (75 MB each) would inflate the stated RSS
    expected = {i: {k: v for k, v in offline_maps(setup, i).items() if k != "cube"} for i in range(R)}
    echo(f"stream bench: {width} x {height}, K = {setup.plan.K}, {setup.plan.A.shape[0]} bands, "
         f"{R} recorded sequences replayed (setup {time.perf_counter() - t_setup:.1f} s)")
    common = {"reference": setup.reference, "device": device}
    rows = []

    def load():
        return os.getloadavg()[0] if hasattr(os, "getloadavg") else None

    sustained = [c for c in _SUSTAINED if c in cases or (c == "linear" and "motion" in cases)
                 or (c in ("static", "full") and {"static", "full"} & set(cases))]
    steps = {}  # the motion case's seconds per step, summed over its rounds
    runs = {c: [] for c in sustained}

    def case_stream(c, count):
        name, outputs, white = cases_run[c]
        return Stream(setup.driver(), setup.plan, setup.bundle, outputs=outputs, policy="block",
                      sinks=[lambda r: count.__setitem__(0, count[0] + 1)],
                      white_roi=white_tile_roi(height, width) if white else None,
                      denoise=(DENOISE_RADIUS, DENOISE_EPS) if c in _DENOISED else None,
                      motion=_MOTION.get(c, "none"),
                      **{k: v for k, v in common.items() if k != "reference" or "dE" in outputs})

    for c in sustained:
        if c in ("motion", "motion_flow", *_DENOISED):  # kernels built at the first sequence: not in the timed run
            case_stream(c, [0]).run(0.5)
    for r in range(int(rounds)):
        for c in sustained:  # interleaved: a change of the machine's load falls on every case alike
            say(f"case {c}, {seconds:g} s" + (f" (round {r + 1} of {rounds})" if rounds > 1 else ""))
            count = [0]
            stream = case_stream(c, count)
            rep = stream.run(seconds)
            if c == "motion":
                for step, s in stream.decoder.seconds.items():
                    steps[step] = steps.get(step, 0.0) + s
                steps["sequences"] = steps.get("sequences", 0) + stream.decoder.sequences
            runs[c].append((rep, load()))
    targets = stream_targets(width, height)
    for c in sustained:
        name = cases_run[c][0]
        order = sorted(range(len(runs[c])), key=lambda i: runs[c][i][0].frames_per_s)
        rep, load_avg = runs[c][order[len(order) // 2]]
        rows.append(_stream_row(name, rep, target_fps=None if c in ("dE_sigma", "linear", "static", *_DENOISED,
                                                                    *_MOTION) else
                                targets.get("coefficients_XYZ_dE2000_fps"),
                                extra={"load_avg_1min": load_avg, "rounds": len(runs[c]),
                                       "frames_per_s_rounds": [r.frames_per_s for r, _ in runs[c]],
                                       "load_avg_rounds": [a for _, a in runs[c]]}))
    if "motion" in cases:
        rows.append(_motion_row(rows, steps))
    if "full" in runs and "static" in runs:
        rows.append(_full_row(rows, runs["full"], runs["static"], cases_run))
    if "paced_full" in cases:
        say(f"case paced_full, {paced_seconds:g} s")
        stream = Stream(setup.driver(pacing="paced"), setup.plan, setup.bundle, outputs=full_outputs,
                        policy="drop_newest", sinks=[], white_roi=white_tile_roi(height, width),
                        denoise=(DENOISE_RADIUS, DENOISE_EPS), motion="global", **common)
        rep = stream.run(paced_seconds)
        passed = (rep.assembly.dropped == 0 and rep.ring.dropped == 0 and rep.assembly.sequences_discarded == 0
                  and rep.sequences_out > 0 and rep.frames_in == setup.plan.K * rep.sequences_out)
        rows.append(_stream_row(f"paced_full {1 / setup.description.camera.frame_rate_hz * 1e3:.0f} ms period: "
                                "--motion global --denoise --white-roi", rep,
                                extra={"camera_fps": setup.description.camera.frame_rate_hz, "passed": passed,
                                       "load_avg_1min": load()}))
    if "cube" in cases:
        say(f"case cube, {seconds:g} s")
        shape, _ = (height, width, setup.plan.A.shape[0]), None
        recorder = MemoryRecorder(shape, np.float16)
        stream = Stream(setup.driver(), setup.plan, setup.bundle, outputs=("cube",), cube_dtype=np.float16,
                        policy="block", sinks=[recorder], device=device)
        rep = stream.run(seconds)
        rows.append(_stream_row("cube float16 61 bands to memory", rep, target_fps=targets.get("cube_float16_fps"),
                                extra={"cubes_written": recorder.count, "load_avg_1min": load()}))
    if "paced" in cases:
        say(f"case paced, {paced_seconds:g} s")
        checker = Checker(setup, expected, ("XYZ", "dE"))
        stream = Stream(setup.driver(pacing="paced"), setup.plan, setup.bundle, outputs=("coefficients", "XYZ", "dE"),
                        policy="drop_newest", sinks=[checker], **common)
        rep = stream.run(paced_seconds)
        acc = rep.accounting()
        passed = (rep.assembly.dropped == 0 and rep.ring.dropped == 0 and checker.misaligned == 0
                  and rep.assembly.sequences_discarded == 0 and acc["balanced"] and checker.checked > 0
                  and rep.frames_in == setup.plan.K * rep.sequences_out)
        rows.append(_stream_row(f"paced {1 / setup.description.camera.frame_rate_hz * 1e3:.0f} ms period", rep,
                                extra={"camera_fps": setup.description.camera.frame_rate_hz,
                                       "checked": checker.checked, "misaligned": checker.misaligned,
                                       "passed": passed, "load_avg_1min": load()}))
    if "overload" in cases:
        say(f"case overload, {overload_seconds:g} s")
        checker = Checker(setup, expected, ("XYZ", "dE"))
        stream = Stream(setup.driver(), setup.plan, setup.bundle, outputs=("cube", "XYZ", "dE"),
                        cube_dtype=np.float32, policy="drop_newest", sinks=[checker], **common)
        rss = []  # resident memory sampled through the run: bounded means flat, not growing with time
        rep = stream.run(overload_seconds, on_status=lambda _s: rss.append(current_rss_bytes()),
                         status_interval_s=0.25)
        half = len(rss) // 2
        acc = rep.accounting()
        total = rep.end.last_frame_id + 1  # the replay loses nothing itself: every id exposed was offered
        passed = (rep.frames_in == total and rep.ring.dropped_newest == rep.assembly.dropped and acc["balanced"]
                  and rep.ring.dropped > 0 and checker.misaligned == 0 and checker.checked == rep.sequences_out)
        rows.append(_stream_row("overload (free-running replay, drop_newest)", rep,
                                extra={"frames_offered": total, "checked": checker.checked,
                                       "frames_into_ring_per_s": rep.ring.finalized / rep.seconds,
                                       "rss_first_half_max_bytes": max(rss[:half] or [0]),
                                       "rss_second_half_max_bytes": max(rss[half:] or [0]),
                                       "misaligned": checker.misaligned, "passed": passed,
                                       "load_avg_1min": load()}))
    if "equality" in cases:
        say("case equality (each recorded sequence once)")
        got = {}

        def keep(result):
            i = setup.recorded_sequence(result.frame_ids)
            if i not in got:
                got[i] = {k: v.copy() for k, v in result.arrays.items()}

        stream = Stream(setup.driver(loops=1), setup.plan, setup.bundle, outputs=("cube", "XYZ", "Lab", "dE"),
                        cube_dtype=np.float32, policy="block", sinks=[keep], **common)
        rep = stream.run()
        expected = {i: offline_maps(setup, i) for i in range(R)}
        diffs = {name: max(max_rel(got[i][name], expected[i][name]) for i in got) for name in ("cube", "XYZ", "Lab")}
        diffs["dE_abs"] = max(float(np.max(np.abs(got[i]["dE"] - expected[i]["dE"]))) for i in got)
        passed = len(got) == R and all(v <= 1e-4 for k, v in diffs.items() if k != "dE_abs") and diffs["dE_abs"] < 1e-2
        rows.append({"case": "stream vs offline pipeline.recover", "sequences": len(got), "max_rel_diff": diffs,
                     "passed": passed, "sequences_out": rep.sequences_out})

    report = {"device": get_queue(device).device.name.strip(), "width": width, "height": height,
              "K": setup.plan.K, "bands": int(setup.plan.A.shape[0]), "cpu_count": os.cpu_count(),
              "source": "ReplayDriver of a twin recording (pre-rendered frames, replayed at memory speed or paced)",
              "cases": rows}
    echo(format_stream_report(report))
    if json_path is not None:
        Path(json_path).write_text(json.dumps(report, indent=2, default=float) + "\n")
    return report


def _stderr_line(text: str) -> None:
    print(f"stream bench: {text} ...", file=sys.stderr, flush=True)


def _motion_row(rows, steps) -> dict:
    """The motion case's rate beside the static one of the same run (the linear case), their ratio, and the host
    milliseconds per sequence of each step of the compensated decoding."""
    fps = {r["case"]: r["frames_per_s"] for r in rows}
    moving, still = fps[_SUSTAINED["motion"][0]], fps[_SUSTAINED["linear"][0]]
    n = max(int(steps.get("sequences", 0)), 1)
    return {"case": "motion global / static", "motion_frames_per_s": moving, "static_frames_per_s": still,
            "ratio": moving / still if still > 0 else float("nan"),
            "ms_per_sequence": {k: v / n * 1e3 for k, v in steps.items() if k != "sequences"}}


def quality_outputs(setup) -> tuple:
    """The outputs the static, full and paced_full cases compare: coefficients + XYZ + dE2000, and ``sigma_rms``
    where the stream's decoder takes it with ``--motion global --denoise --white-roi`` (``setup.plan`` with its
    noise model); where it refuses that (the sigma not carried through the filter), the three alone."""
    h, w = setup.frames.shape[1:]
    outputs = (*_QUALITY_OUTPUTS, _QUALITY_SIGMA)
    try:
        SequenceDecoder(setup.plan, setup.bundle, outputs, reference=setup.reference, frame_shape=(h, w),
                        white_roi=white_tile_roi(h, w), denoise=(DENOISE_RADIUS, DENOISE_EPS), motion="global")
    except ValueError:
        return _QUALITY_OUTPUTS
    return outputs


def _full_row(rows, full, static, cases_run) -> dict:
    """Full quality beside static of the same rounds (interleaved, so a change of load falls on both): their
    median rates (the rows already made of them), each round's ratio, and the median ratio against
    :data:`FULL_RATIO_TARGET`."""
    fps = {r["case"]: r["frames_per_s"] for r in rows}
    ratios = sorted(f.frames_per_s / s.frames_per_s if s.frames_per_s > 0 else float("nan")
                    for (f, _), (s, _) in zip(full, static))
    median = float(np.median(ratios))
    return {"case": "full / static", "full_frames_per_s": fps[cases_run["full"][0]],
            "static_frames_per_s": fps[cases_run["static"][0]], "outputs": list(cases_run["full"][1]),
            "ratio": median, "ratio_rounds": ratios,
            "target_ratio": FULL_RATIO_TARGET, "passed": bool(median >= FULL_RATIO_TARGET)}


def format_stream_report(report: dict) -> str:
    """The stream benchmark as text: one block per case with its figures and PASS / MISS."""
    lines = [(f"stream on {report['device']} ({report['cpu_count']} CPUs), {report['width']} x "
              f"{report['height']}, K = {report['K']}; source: {report['source']}")]
    for row in report["cases"]:
        mark = {True: "PASS", False: "MISS", None: "    "}[row.get("passed")]
        if "full_frames_per_s" in row:
            lines.append(f"{mark}  {row['case']}: {row['full_frames_per_s']:.0f} frames/s with --motion global "
                         f"--denoise --white-roi, {row['static_frames_per_s']:.0f} static (medians"
                         + (f"; outputs {'+'.join(row['outputs'])}" if row.get("outputs") else "") + "), ratio "
                         f"{row['ratio']:.3f} (median of " + ", ".join(f"{v:.3f}" for v in row["ratio_rounds"])
                         + f"; target >= {row['target_ratio']:.2f})")
            continue
        if "ratio" in row:
            lines.append(f"{mark}  {row['case']}: {row['motion_frames_per_s']:.0f} frames/s with --motion global, "
                         f"{row['static_frames_per_s']:.0f} static, ratio {row['ratio']:.3f}; ms per sequence: "
                         + ", ".join(f"{k} {v:.1f}" for k, v in row["ms_per_sequence"].items()))
            continue
        if "frames_per_s" not in row:
            lines.append(f"{mark}  {row['case']}: {row['sequences']} sequences, max relative difference "
                         + ", ".join(f"{k} {v:.2e}" for k, v in row["max_rel_diff"].items()))
            continue
        rss = row["peak_rss_bytes"]
        target = f" (target >= {row['target_fps']:.0f})" if "target_fps" in row else ""
        lines.append(
            f"{mark}  {row['case']}: {row['frames_per_s']:.0f} frames/s in{target}, {row['sequences_per_s']:.1f} "
            f"sequences/s out over {row['seconds']:.1f} s; latency median {row['latency_ms_median']:.1f} ms, "
            f"p99 {row['latency_ms_p99']:.1f} ms; ring drops {row['ring']['dropped']}, id gaps "
            f"{row['assembly']['dropped']}, discarded {row['assembly']['sequences_discarded']}; CPU "
            f"{row['cpu_cores']:.2f} cores; peak RSS {rss / 2**20:.0f} MiB"
            + (f"; checked {row['checked']}, misaligned {row['misaligned']}" if "checked" in row else "")
            + (f"; offered {row['frames_offered']} ({row['frames_into_ring_per_s']:.0f}/s into the ring); RSS max "
               f"{row['rss_first_half_max_bytes'] / 2**20:.0f} MiB in the first half, "
               f"{row['rss_second_half_max_bytes'] / 2**20:.0f} MiB in the second" if "frames_offered" in row else "")
            + (f"; RSS at start {row['rss_start_bytes'] / 2**20:.0f} MiB" if row.get("rss_start_bytes") else "")
            + (f"; load {row['load_avg_1min']:.2f}" if row.get("load_avg_1min") is not None else "")
            + (f"; median of {row['rounds']} rounds: " + ", ".join(f"{v:.0f}" for v in row["frames_per_s_rounds"])
               + " frames/s at load " + ", ".join(f"{v:.2f}" for v in row["load_avg_rounds"] if v is not None)
               if row.get("rounds", 1) > 1 else ""))
    return "\n".join(lines)


# ------------------------------------------------------------------------------------- the bench's sinks

def max_rel(a, b) -> float:
    """The largest absolute difference of ``a`` from ``b`` relative to the largest magnitude of ``b``."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-12))


class Checker:
    """A sink that checks every result against the offline maps of the recorded sequence it must come from:
    consecutive frame ids, starting at pattern 0, and equal maps (a misaligned sequence cannot pass)."""

    def __init__(self, setup: StreamSetup, expected: dict, outputs, tolerance: float = 1e-3):
        self.setup, self.expected, self.outputs, self.tolerance = setup, expected, outputs, tolerance
        self.checked = 0
        self.misaligned = 0
        self.worst = 0.0

    def write(self, result):
        K = self.setup.plan.K
        ids = result.frame_ids
        ok = bool(np.all(np.diff(ids) == 1)) and int(ids[0]) % K == 0
        exp = self.expected[self.setup.recorded_sequence(ids)]
        for name in self.outputs:
            if name in exp and name in result.arrays:
                if name == "dE":
                    err = float(np.max(np.abs(result.arrays[name] - exp[name])))  # dE units
                else:
                    err = max_rel(result.arrays[name], exp[name])
                self.worst = max(self.worst, err)
                ok = ok and err <= (2e-3 if name != "dE" else 0.05)
        self.checked += 1
        self.misaligned += not ok

    def close(self):
        pass


class MemoryRecorder:
    """A sink that writes every result's cube into a preallocated in-memory recording (a ring of ``slots``)."""

    def __init__(self, shape, dtype, slots: int = 4):
        self.store = np.zeros((slots, *shape), dtype)
        self.count = 0

    def write(self, result):
        np.copyto(self.store[self.count % len(self.store)], result.arrays["cube"])
        self.count += 1

    def close(self):
        pass
