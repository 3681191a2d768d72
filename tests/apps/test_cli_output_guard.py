"""The output guard on the command line: every command that writes refuses, before any work, an output that is one
of its inputs, lies inside a folder it reads whole (a recording, a moving capture's truth), holds an input, or is a
file its inputs refer to (a capture's frames, plan and calibration, a scene file a rig names), as a usage error
naming both paths; the input stays byte for byte as it was."""

from __future__ import annotations

import os
import shutil

import pytest
from cli_helpers import MOVING_RIG, one_line_error, run


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A moving twin (its rig names a scene file), its calibration and a Hadamard plan, a capture of two sequences
    with their truth, a zarr recording of one, and a cube recovered from the capture's first sequence."""
    from specgpu.calibration.bundle import oracle_calibration, save_calibration
    from specgpu.rig.config import load_rig

    d = tmp_path_factory.mktemp("guard")
    (d / "rig.toml").write_text(MOVING_RIG)
    save_calibration(d / "calib.npz", oracle_calibration(load_rig(d / "rig.toml")))
    run("plan", "hadamard", "--bands", "7", "--calib", d / "calib.npz", "--rig", d / "rig.toml", "--out",
        d / "plan.npz", "--no-ambient")
    common = ("--rig", d / "rig.toml", "--plan", d / "plan.npz", "--calib", d / "calib.npz", "--seed", "1")
    run("capture", *common, "--out", d / "seqm", "--sequences", "2")
    run("capture", *common, "--out", d / "rec.zarr", "--sequences", "1")
    run("recover", d / "seqm", "--sequence", "0", "--out", d / "m.npz")
    shutil.copyfile(d / "seqm" / "motion_truth" / "sequence_0000.npz", d / "scene.npz")
    (d / "scene-rig.toml").write_text(MOVING_RIG.replace('source = "natural"', 'source = "scene.npz"'))
    return d


@pytest.fixture
def w(made, tmp_path):
    """A private copy of the fixture's files (a failing guard would damage only this test's copy)."""
    shutil.copytree(made, tmp_path / "w")
    return tmp_path / "w"


FRAME = "frame_000003.tif"
SEQ_FILES = ("sequence.json", FRAME, "plan.npz", "calibration.npz")
TRUTH = "motion_truth/sequence_0001.npz"


def _report(w, name):
    (w / "run").mkdir()
    shutil.move(w / "seqm", w / "run" / "a")
    return ["report", w / "run", "--out", w / "run" / "a" / name], w / "run" / "a" / name


def _evaluate(w, name):
    return ["evaluate", w / "m.npz", "--truth", w / "seqm", "--json", w / "seqm" / name], w / "seqm" / name


def _recover(w, option, name):
    extra = ["--delta-e-ref", "50,0,0"] if option == "--delta-e" else []
    target = w / "seqm" / name
    args = ["recover", w / "seqm", "--sequence", "0", "--motion", "global", "--out", w / "c.npz", *extra,
            option, target]
    if option == "--out":
        args = ["recover", w / "seqm", "--sequence", "0", "--motion", "global", "--out", target]
    return args, target


def _holding(w, command):
    """A folder output that holds one of the command's inputs (the plan): writing into it could replace it."""
    (w / "box").mkdir()
    shutil.move(w / "plan.npz", w / "box" / "plan.npz")
    common = ["--rig", w / "rig.toml", "--plan", w / "box" / "plan.npz", "--calib", w / "calib.npz"]
    if command == "capture":
        return ["capture", *common, "--out", w / "box"], w / "box" / "plan.npz"
    if command == "stream":
        return ["stream", *common, "--seconds", "0.2", "--out", w / "box"], w / "box" / "plan.npz"
    return ["batch", w / "rec.zarr", "--plan", w / "box" / "plan.npz", "--calib", w / "calib.npz", "--out",
            w / "box"], w / "box" / "plan.npz"


CASES = {
    **{f"report-onto-{n}": (lambda w, n=n: _report(w, n)) for n in SEQ_FILES},
    **{f"evaluate-json-onto-{n}": (lambda w, n=n: _evaluate(w, n)) for n in (*SEQ_FILES, TRUTH)},
    "evaluate-json-onto-cube": lambda w: (["evaluate", w / "m.npz", "--truth", w / "seqm", "--json", w / "m.npz"],
                                          w / "m.npz"),
    "recover-out-onto-truth": lambda w: _recover(w, "--out", "motion_truth/sequence_0000.npz"),
    "recover-xyz-onto-plan": lambda w: _recover(w, "--xyz", "plan.npz"),
    "recover-lab-onto-frame": lambda w: _recover(w, "--lab", FRAME),
    "recover-delta-e-onto-index": lambda w: _recover(w, "--delta-e", "sequence.json"),
    "recover-sigma-onto-calibration": lambda w: _recover(w, "--sigma", "calibration.npz"),
    "recover-delta-e-sigma-onto-truth": lambda w: _recover(w, "--delta-e-sigma", TRUTH),
    "calibrate-onto-rig": lambda w: (["calibrate", "--rig", w / "rig.toml", "--out", w / "rig.toml"],
                                     w / "rig.toml"),
    "calibrate-onto-the-rigs-scene": lambda w: (["calibrate", "--rig", w / "scene-rig.toml", "--out",
                                                 w / "scene.npz"], w / "scene.npz"),
    "plan-onto-calibration": lambda w: (["plan", "hadamard", "--bands", "7", "--calib", w / "calib.npz", "--out",
                                         w / "calib.npz"], w / "calib.npz"),
    "plan-onto-training": lambda w: (["plan", "symmetric", "--calib", w / "calib.npz", "--training", w / "scene.npz",
                                      "--out", w / "scene.npz"], w / "scene.npz"),
    "capture-into-a-folder-holding-its-plan": lambda w: _holding(w, "capture"),
    "capture-onto-the-rigs-scene-folder": lambda w: (["capture", "--rig", w / "rig.toml", "--plan", w / "plan.npz",
                                                      "--calib", w / "calib.npz", "--scene", w / "seqm" / TRUTH,
                                                      "--out", w / "seqm" / "motion_truth"], w / "seqm" / TRUTH),
    "stream-into-a-folder-holding-its-plan": lambda w: _holding(w, "stream"),
    "batch-into-a-folder-holding-its-plan": lambda w: _holding(w, "batch"),
    "batch-inside-its-recording": lambda w: (["batch", w / "rec.zarr", "--plan", w / "plan.npz", "--calib",
                                              w / "calib.npz", "--out", w / "rec.zarr" / "out.zarr"],
                                             w / "rec.zarr" / "zarr.json"),
    "batch-inside-its-capture's-truth": lambda w: (["batch", w / "seqm", "--plan", w / "plan.npz", "--out",
                                                    w / "seqm" / "motion_truth" / "b.zarr"], w / "seqm" / TRUTH),
    "demo-into-the-folder-of-its-rig": lambda w: (["demo", "--rig", w / "rig.toml", "--out", w], w / "rig.toml"),
}


OUTPUT_OPTIONS = ("--out", "--json", "--xyz", "--lab", "--delta-e", "--sigma", "--delta-e-sigma")


@pytest.mark.parametrize("case", sorted(CASES))
def test_an_output_on_an_input_is_a_usage_error_naming_both(w, case):
    args, victim = CASES[case](w)
    output = args[max(i for i, a in enumerate(args) if a in OUTPUT_OPTIONS) + 1]  # the output the case aims
    before = victim.read_bytes()
    result = run(*args, ok=False)
    line = one_line_error(result, output, code=2)
    assert str(victim) in line or str(victim.parent) in line, line  # the input: the file, or the folder holding it
    assert victim.read_bytes() == before


def test_an_output_reached_through_a_symbolic_link_is_refused(w):
    (w / "link.json").symlink_to(w / "seqm" / "sequence.json")
    before = (w / "seqm" / "sequence.json").read_bytes()
    result = run("evaluate", w / "m.npz", "--truth", w / "seqm", "--json", w / "link.json", ok=False)
    one_line_error(result, w / "link.json", w / "seqm" / "sequence.json", code=2)
    assert (w / "seqm" / "sequence.json").read_bytes() == before


def test_an_output_in_a_linked_folder_of_the_truth_is_refused(w):
    os.symlink(w / "seqm" / "motion_truth", w / "truths")
    before = (w / "seqm" / TRUTH).read_bytes()
    result = run("recover", w / "seqm", "--sequence", "1", "--out", w / "truths" / "sequence_0001.npz", ok=False)
    one_line_error(result, w / "truths" / "sequence_0001.npz", "motion_truth", code=2)
    assert (w / "seqm" / TRUTH).read_bytes() == before


def test_a_new_file_beside_a_capture_is_still_allowed(w):
    """A report or a cube beside a capture's files destroys nothing: the report's default is there."""
    run("recover", w / "seqm", "--sequence", "0", "--out", w / "seqm" / "cube.npz")
    # decoded as if still, the moving capture leaves a few implausible pixels at its edges: scored without them
    run("evaluate", w / "seqm" / "cube.npz", "--truth", w / "seqm", "--json", w / "seqm" / "score.json",
        "--exclude-invalid")
    assert (w / "seqm" / "score.json").is_file()
