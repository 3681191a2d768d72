"""What the commands of ``specgpu`` share: the command class that turns any error into one line, the options
several commands take, and the guards around outputs (no output on an input or on another output, an exclusive
lock on each, all-or-nothing writes), the progress line and the scene and reference parsing."""

from __future__ import annotations

import dataclasses
import math
import os
import signal
import sys
import threading
from pathlib import Path

import click
import numpy as np
from tqdm import tqdm

from specgpu.apps.cli.group import watch_outputs
from specgpu.calibration.bundle import load_calibration
from specgpu.core.guard import check_outputs
from specgpu.core.locks import output_locks
from specgpu.core.numerics import one_blas_thread
from specgpu.core.spectra import DEFAULT_CMFS, resolve_integration
from specgpu.core.validate import BadArgument, validate_method
from specgpu.engine.colorimetry import XYZ_to_Lab
from specgpu.io import JOURNAL_FILE, SEQUENCE_FILE
from specgpu.io.cube import companion_files
from specgpu.io.motion_truth import TRUTH_FOLDER
from specgpu.io.paths import final_names, new_temporary, replace_with, write_target
from specgpu.pipeline.capture_folder import CALIBRATION_FILE, PLAN_FILE
from specgpu.pipeline.evaluate import scene_XYZ
from specgpu.planning.plans import load_plan
from specgpu.rig.config import load_rig
from specgpu.rig.scene import SpectralScene, load_scene, validate_resize


class Command(click.Command):
    """A command whose errors are one line on stderr: exit status 2 for a bad argument (an unknown name, an output
    over an input: :class:`specgpu.core.validate.BadArgument`, wherever below it is found), 1 for any other
    failure (click's own errors, usage errors and interrupts pass through to the group)."""

    def invoke(self, ctx):
        one_blas_thread()  # small host matrices: BLAS threads on busy cores only wait on each other
        try:
            return super().invoke(ctx)
        except (click.ClickException, click.exceptions.Exit, click.exceptions.Abort, SystemExit,
                KeyboardInterrupt):
            raise
        except BadArgument as error:
            raise click.UsageError(final_names(str(error)).strip().splitlines()[0]) from error
        except Exception as error:  # the CLI promises one line, not a traceback
            text = final_names(str(error)).strip()  # an output's name, never its temporary's
            message = text.splitlines()[0] if text else type(error).__name__
            raise click.ClickException(message) from error


def command(name=None, **kwargs):
    """``click.command`` with :class:`Command` and the group's ``-h`` / ``--help``."""
    return click.command(name, cls=Command, context_settings={"help_option_names": ["-h", "--help"]}, **kwargs)


def with_companions(named):
    """(option, path) pairs with each path's companion files (an ENVI header's data file) added after it."""
    out = []
    for opt, path in named:
        if path is None:
            continue
        out.append((opt, path))
        out += [(f"{opt}'s ENVI data file", c) for c in companion_files(path)]
    return out


def sequence_files(seq, label="SEQ"):
    """What reading the capture folder ``seq`` reads: its index, journal, plan, calibration and frames, and its
    ``motion_truth`` folder whole. A new file beside them (a report, a cube) changes none of it."""
    folder = Path(seq)
    names = (SEQUENCE_FILE, JOURNAL_FILE, PLAN_FILE, CALIBRATION_FILE, TRUTH_FOLDER)
    files = [(f"{label}'s {name}", folder / name) for name in names]
    return files + [(f"{label}'s {p.name}", p) for p in sorted(folder.glob("frame_*.tif"))]


def is_capture(folder) -> bool:
    folder = Path(folder)
    return any((folder / name).exists() for name in (SEQUENCE_FILE, JOURNAL_FILE)) or \
        next(folder.glob("frame_*.tif"), None) is not None


def rig_files(rig_path):
    """The files a rig TOML names (a scene cube, a moving object, CSV curves): inputs of whoever reads the rig.
    A rig that does not load names none here (the command refuses it with its own message)."""
    try:
        description = load_rig(rig_path)
    except (ValueError, OSError):
        return []
    found, todo = [], [description]
    while todo:
        item = todo.pop()
        for field in dataclasses.fields(item):
            value = getattr(item, field.name)
            if dataclasses.is_dataclass(value):
                todo.append(value)
            elif isinstance(value, str) and value and os.path.isfile(value):
                found.append((f"{rig_path}'s {field.name}", value))
    return found


def read_paths(label, path):
    """Everything reading the input ``path`` reads: a capture folder's files (:func:`sequence_files`), any
    other folder whole (a zarr recording), a file with its companions and, for a rig TOML, the files it names.
    A name that is no path on disk (a built-in scene) reads nothing here."""
    if path is None or not os.path.exists(path):
        return []
    if os.path.isdir(path):
        return sequence_files(path, label) if is_capture(path) else [(label, path)]
    found = with_companions([(label, path)])
    return found + rig_files(path) if str(path).lower().endswith(".toml") else found


def no_clash(outputs, inputs=()):
    """The output guard (:func:`specgpu.core.guard.check_outputs`) of every command that writes: ``outputs`` and
    ``inputs`` are (option, path) pairs, each input expanded to all that reading it reads (:func:`read_paths`).
    Refuses, as a usage error naming both paths, an output that is an input, lies inside a folder read whole,
    holds an input, or names the same file as another output (companions count: an ENVI header's data file is
    written with it). The outputs are watched from here on, so an interrupt can say which were written."""
    outputs = with_companions(outputs)
    check_outputs(outputs, [pair for label, path in inputs for pair in read_paths(label, path)])
    watch_outputs(path for _, path in outputs)


class Staged:
    """Outputs written all or nothing: each to a temporary name beside its final one, renamed over the finals
    only once every one is written (with SIGINT / SIGTERM held back during the renames); on failure the temporaries
    are removed and the finals, old files included, are untouched."""

    def __init__(self):
        self.pairs = []  # (temporary, final), each output's companions before it
        self.outputs = []  # the finals asked for, in order

    def path(self, final):
        final = write_target(final)  # through a symbolic link, as a plain open() writes
        tmp = new_temporary(final)  # the mode a plain open() gives, not mkstemp's 0600
        self.pairs.append((tmp, final))
        return tmp

    def write(self, final, write, companions=()):
        """``write(path)`` to a temporary beside ``final``; an error names ``final``, never the temporary.
        ``companions``: suffixes of files the writer puts beside its path (an ENVI header's ``.img``), renamed with
        it, before it."""
        tmp = self.path(final)
        self.outputs.append(Path(final))
        for suffix in companions:
            self.pairs.insert(len(self.pairs) - 1, (tmp.with_suffix(suffix),
                                                    write_target(Path(final).with_suffix(suffix))))
        try:
            write(tmp)
        except Exception as error:  # the temporaries' names (a companion's too) are never what the user sees
            text = str(error).replace(str(tmp), str(final))
            if final_names(text) != str(error):
                raise click.ClickException(final_names(text).splitlines()[0]) from error
            raise

    def discard(self):
        for tmp, _ in self.pairs:
            tmp.unlink(missing_ok=True)

    def commit(self):
        held = {signal.SIGINT, signal.SIGTERM}
        old = signal.pthread_sigmask(signal.SIG_BLOCK, held)
        try:
            for tmp, final in self.pairs:
                replace_with(tmp, final)  # a file replaced keeps its mode
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)
        return self.outputs

    def write_all(self, writes):
        """Stage every ``(final, write[, companions])`` and commit them; on any failure none is replaced."""
        try:
            for final, write, *companions in writes:
                self.write(final, write, *companions)
            return self.commit()
        except BaseException:
            self.discard()
            raise


def lock(*paths, folder: bool = False):
    """Hold the exclusive lock of these outputs until the command ends (a second writer refuses at once);
    ``folder``: output folders, whose missing parents are created. An output's companion files (an ENVI header's
    data file) are locked with it; every lock is on the resolved path (see :mod:`specgpu.core.locks`)."""
    if not folder:
        paths = [p for _, p in with_companions((None, p) for p in paths)]
    click.get_current_context().with_resource(output_locks(paths, make_parents=folder))


class Finite(click.FloatRange):
    """A float in a range that is also finite (click's FloatRange lets NaN through every bound)."""

    def convert(self, value, param, ctx):
        rv = super().convert(value, param, ctx)
        if not math.isfinite(rv):
            self.fail(f"{value!r} is not a finite number.", param, ctx)
        return rv


RIG = click.option("--rig", "rig_path", type=click.Path(dir_okay=False), default=None,
                   help="Rig description TOML (default: the paper's rig, simulated by the digital twin).")
PLAN = click.option("--plan", "plan_path", required=True, type=click.Path(exists=True, dir_okay=False),
                    help="Plan (specgpu plan).")
SCENE = click.option("--scene", default=None, help="Scene: colorchecker, white, natural[:image], or a .exr / .npz "
                                                  "/ .hdr (ENVI) cube (default: the rig's [scene] source).")
DEVICE = click.option("--device", "device", default=None, help="OpenCL device selector.")


def resize_mode(ctx, param, value):
    try:
        return validate_resize(value)
    except ValueError as error:
        raise click.BadParameter(str(error)) from None


RESIZE = click.option(
    "--resize", default="scale", show_default=True, callback=resize_mode, metavar="scale|exact|stretch|crop|pad",
    help="How a scene file of another size than the frame is fitted (nearest neighbour; what was done is printed "
         "and recorded): scale uniformly, refusing another aspect ratio; exact: refuse any resampling; stretch: "
         "each axis on its own (the aspect ratio changes); crop: scale to cover, centre-crop; pad: scale to fit, "
         "centre, black border.")

ILLUMINANT = click.option(
    "--illuminant", default=None,
    help="Illuminant of XYZ, Lab and dE, recorded with every output [default: the plan's own for a tristimulus or "
         "camera plan, else D65]; another than a tristimulus or camera plan measures under is refused.")

def integration_option(default="rectangle", note=""):
    """``--integration``: how reflectance is integrated to XYZ (the white of Lab and dE with it), checked as a
    usage error naming the option."""

    def check(ctx, param, value):
        try:
            return None if value is None else resolve_integration(value)
        except ValueError as error:
            raise click.BadParameter(str(error)) from None

    return click.option(
        "--integration", default=default, show_default=default is not None, callback=check,
        metavar="rectangle|astm-e308",
        help="How reflectance is integrated to XYZ, and the white of Lab and dE with it: the rectangle rule on the "
             "cube's own grid, or ASTM E308's tables (what colorimetry software and instruments report; grids of "
             "1, 5, 10 or 20 nm)." + note)


INTEGRATION = integration_option()


OBSERVER = click.option(
    "--observer", default=None,
    help="Observer (colour-matching functions) of XYZ, Lab and dE, recorded with every output [default: the plan's "
         "own for a tristimulus plan, else CIE 1931 2 Degree Standard Observer]; another than a tristimulus plan's "
         "is refused.")


def resampled(what, scene, meta=None, key="scene_resampled"):
    """Say on stderr (one line naming ``what``, e.g. '--scene s.npz') and in ``meta`` how a scene file was fitted
    to the frame; returns ``scene``."""
    if scene.resampled:
        # through tqdm: a line of its own even while a progress line is shown
        tqdm.write(f"specgpu: {what}: resampled {scene.resampled}", file=sys.stderr)
        if meta is not None:
            meta[key] = scene.resampled
    return scene


def experiment(description, plan_path, calib, scene, resize="scale"):
    """The rig's calibration, a plan made from that calibration (stale: an error) and the scene at the camera's
    resolution (fitted by ``resize``, said on stderr): what capture and stream both start from."""
    bundle = load_calibration(calib, rig=description)
    plan = load_plan(plan_path)
    plan.check_calibration(bundle, name=str(plan_path), calibration_name=str(calib))
    cam = description.camera
    truth = load_scene(scene or description.scene, cam.roi_height, cam.roi_width, resize=resize)
    return bundle, plan, resampled(f"--scene {scene}" if scene else f"the rig's scene {description.scene}", truth)


class Busy:
    """A progress line with elapsed time for a step of unknown length (tqdm, refreshed from a thread)."""

    def __init__(self, desc: str):
        self._bar = tqdm(total=None, desc=desc, bar_format="{desc}: {elapsed}", leave=False, file=sys.stderr)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._tick, daemon=True)

    def _tick(self):
        while not self._stop.wait(0.2):
            self._bar.refresh()

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self._bar.close()


class one_interrupt:
    """While a stream drains after Ctrl-C (or SIGTERM), further ones are reported, not obeyed: a second Ctrl-C
    would abandon the drain and lose what was captured. ``kill -9`` still stops it at once."""

    def __enter__(self):
        self._previous = {}
        if threading.current_thread() is not threading.main_thread():
            return self
        state = {"seen": False}

        def handler(signum, frame):
            if not state["seen"]:
                state["seen"] = True
                raise KeyboardInterrupt
            click.echo("specgpu: draining what was captured; kill -9 to abandon it", err=True)

        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, handler)
        return self

    def __exit__(self, *exc):
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)


def parse_reference(text, height, width, illuminant, resize="scale", meta=None, observer=None,
                    integration="rectangle"):
    """--delta-e-ref: an 'L,a,b' colour, or a scene (built-in name, cube file, or a loaded scene) whose Lab (under
    ``illuminant`` for ``observer``, None: the 2 degree observer; integrated by ``integration`` on the scene's
    bands, with the white of that grid) is the reference; a scene file of another size is fitted by ``resize``,
    said on stderr and in ``meta``."""
    parts = [] if isinstance(text, SpectralScene) else text.split(",")
    if len(parts) == 3:
        try:
            lab = np.array([float(p) for p in parts], np.float64)
        except ValueError:
            lab = None
        if lab is not None:  # a colour: NaN or 1e40 would make every dE NaN, silently
            if not (np.all(np.isfinite(lab)) and 0 <= lab[0] <= 200 and np.all(np.abs(lab[1:]) <= 500)):
                raise click.BadParameter(f"{text!r} is not a CIELAB colour: give finite 'L,a,b' with L in 0-200 "
                                         "and a, b in -500-500", param_hint="--delta-e-ref")
            return lab.astype(np.float32)
    scene = load_scene(text, height, width, resize=resize)
    if not isinstance(text, SpectralScene):
        resampled(f"--delta-e-ref {text}", scene, meta, "reference_resampled")
    observer = observer or DEFAULT_CMFS
    XYZ = scene_XYZ(scene, illuminant, observer, integration=integration)
    return XYZ_to_Lab(XYZ, illuminant, observer=observer, wavelengths=scene.wavelengths, integration=integration)


def output_list(text, valid, what):
    """A comma-separated list of outputs, each checked against ``valid`` (a typo is an error naming them)."""
    return tuple(validate_method(o.strip(), {k: k for k in valid}, what) for o in text.split(",") if o.strip())


WHITE_ROI_MOVES = click.option(
    "--white-roi-moves", type=click.Choice(["scene", "camera"], case_sensitive=False), default="scene",
    show_default=True, callback=lambda ctx, param, value: value.lower(),
    help="With --motion and --white-roi: the white moves with the scene (measured on the motion-compensated "
         "samples, the ROI where it is at the sequence's reference time) or is fixed in the field (camera: "
         "measured on the raw pixels).")
