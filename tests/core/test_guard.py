"""The output guard against what writing would do: on a small tree of files, folders, symbolic links and a hard
link, an output it lets through changes no input when written, and an output it refuses would have changed one
(or names another output's file)."""

from __future__ import annotations

import hashlib
import os
import secrets
import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from specgpu.core.guard import OutputClash, check_outputs
from specgpu.core.validate import BadArgument

#: every path of the tree below (relative to its root), input candidates and output candidates alike
TREE_FILES = ("a/f1", "a/sub/f2", "b/g", "c.txt")
LINKS = {"la": "a", "lf": "c.txt", "a/lb": "b", "lg": "b/g", "dangling": "gone/new.txt"}
INPUTS = ("a", "a/sub", "a/f1", "a/sub/f2", "b", "b/g", "c.txt", "la", "lf", "lg", "a/lb", "hard.txt")
OUTPUTS = (*INPUTS, "new.txt", "a/new", "a/sub/new", "la/f1", "la/new", "la/sub/f2", "a/lb/g", "a/lb/new",
           "b/new", "newdir/x", "gone/new.txt", "dangling", "./a/../c.txt", "a/sub/../f1", "lf", "d")


def make_tree(root: Path) -> None:
    for name in TREE_FILES:
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(name)
    (root / "d").mkdir()  # an empty folder: an output folder holding nothing read
    for link, target in LINKS.items():
        os.symlink(root / target, root / link)
    os.link(root / "c.txt", root / "hard.txt")  # one file, two names


def snapshot(root: Path, inputs) -> dict:
    """Every byte an input's reader would see: a file's content, every file under a folder (links followed)."""
    seen = {}
    for name in inputs:
        path = root / name
        if path.is_dir():
            for folder, _, files in os.walk(path, followlinks=True):
                for f in files:
                    p = Path(folder, f)
                    seen[(name, str(p.relative_to(path)))] = hashlib.sha256(p.read_bytes()).hexdigest()
        else:
            seen[(name, "")] = hashlib.sha256(path.read_bytes()).hexdigest()
    return seen


def write(path: Path) -> None:
    """What a command does with an output: a file's folder created and the file written through a link, as a
    plain open() does; a folder written into, any file in it replaced (links in it are not followed)."""
    if path.is_dir():
        for folder, _, files in os.walk(path):
            for f in files:
                if not os.path.islink(os.path.join(folder, f)):
                    Path(folder, f).write_text(secrets.token_hex(8))
        (path / f"new-{secrets.token_hex(3)}").write_text("written")
        return
    os.makedirs(os.path.dirname(os.path.realpath(path)), exist_ok=True)
    path.write_text(secrets.token_hex(8))


@settings(max_examples=150, deadline=None)
@given(st.lists(st.sampled_from(INPUTS), max_size=3, unique=True), st.sampled_from(OUTPUTS))
def test_refused_exactly_when_writing_would_change_an_input(inputs, output):
    """A file output: refused if and only if writing it changes an input. A folder output: never let through when
    writing into it changes an input (it is also refused when it merely holds one, which a write may spare)."""
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        make_tree(root)
        before = snapshot(root, inputs)
        folder = (root / output).is_dir()
        try:
            check_outputs([("--out", root / output)], [(f"IN{i}", root / n) for i, n in enumerate(inputs)])
            refused = None
        except OutputClash as error:
            refused = error
        write(root / output)
        changed = snapshot(root, inputs) != before
        if refused is None:
            assert not changed, (inputs, output)
        elif not folder:
            assert changed, (inputs, output, refused)
        if refused is not None:
            assert str(root / output) in str(refused) and str(refused.other) in str(refused)


@settings(max_examples=80, deadline=None)
@given(st.sampled_from(OUTPUTS), st.sampled_from(OUTPUTS))
def test_two_outputs_naming_one_file_are_refused(first, second):
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        make_tree(root)
        one = os.path.realpath(root / first) == os.path.realpath(root / second) or (
            (root / first).exists() and (root / second).exists() and os.path.samefile(root / first, root / second))
        try:
            check_outputs([("--out", root / first), ("--xyz", root / second)])
        except OutputClash as error:
            assert one and "--out and --xyz both name" in str(error)
        else:
            assert not one


def test_a_clash_is_a_bad_argument_naming_both_paths(tmp_path):
    (tmp_path / "seq").mkdir()
    (tmp_path / "seq" / "sequence.json").write_text("{}")
    with pytest.raises(BadArgument, match="--json .*sequence.json is the input SEQ's index"):
        check_outputs([("--json", tmp_path / "seq" / "sequence.json")],
                      [("SEQ's index", tmp_path / "seq" / "sequence.json")])
    with pytest.raises(OutputClash, match="lies inside the input REC"):
        check_outputs([("--out", tmp_path / "seq" / "new.npz")], [("REC", tmp_path / "seq")])
    check_outputs([("--out", tmp_path / "new.npz"), ("--xyz", None)], [("REC", tmp_path / "seq"), ("X", None)])
    shutil.rmtree(tmp_path / "seq")
