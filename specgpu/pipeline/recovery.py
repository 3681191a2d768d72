"""The offline main job as functions: capture a plan's sequences on the twin, keep them with their plan and
calibration in one folder, and recover them; used by the CLI, ``specgpu demo`` and ``tools/studies/accuracy_study.py``.

A sequence folder (``specgpu capture``) holds the frames and ``sequence.json`` (:mod:`specgpu.io.sequence`), plus the
plan (``plan.npz``) and calibration bundle (``calibration.npz``) it was captured with, so ``specgpu recover``
needs nothing else; the hashes chain sequence -> plan -> calibration, and a mismatch is an error naming the
file, never a silent wrong answer.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from specgpu import io
from specgpu.io.journal import journal_header
from specgpu.io.paths import atomic_path
from specgpu.calibration.bundle import CalibrationBundle, load_calibration, save_calibration
from specgpu.capture.session import CaptureResult, capture_sequences
from specgpu.capture.twin_driver import TwinDriver
from specgpu.core.numerics import live_gain
from specgpu.engine.colorimetry import XYZ_to_Lab, reflectance_to_XYZ
from specgpu.engine.linear_map import apply_linear
from specgpu.pipeline.evaluate import true_patch_spectra
from specgpu.pipeline.moving import check_motion_mode
from specgpu.pipeline.motion_record import renumber_truth
from specgpu.pipeline.moving_layers import recover_moving
from specgpu.pipeline.moving_residual import residual_check
from specgpu.planning.basis import DEFAULT_WAVELENGTHS, evaluation_exclusions, load_reflectances, pca_basis
from specgpu.planning.correction import ambient_index, corrected_decoder, white_gains
from specgpu.planning.plans import Plan, load_plan, save_plan
from specgpu.planning.reference_frames import reference_indices
from specgpu.planning.uncertainty import (
    constant_covariance,
    frame_covariance,
    frame_variance,
    output_covariance,
    sigma_map,
)
from specgpu.rig.config import RigDescription
from specgpu.rig.scene import SpectralScene, colorchecker_scene, read_scene
from specgpu.rig.twin import FaultSchedule, TwinRig

__all__ = ["capture_plan", "write_capture", "CaptureWriter", "check_capture_folder", "default_basis", "SequenceFolder",
           "read_capture", "recover", "save_plan_and_calibration", "dark_warning", "to_XYZ", "to_Lab"]

PLAN_FILE = "plan.npz"
#: The chart the demo and the accuracy study evaluate on (and leave out of basis training).
EVALUATION_CHART = "ColorChecker N Ohta"
CALIBRATION_FILE = "calibration.npz"


def capture_plan(description: RigDescription, plan: Plan, scene: SpectralScene, *, sequences: int = 1,
                 noise_seed: int | None = None, faults: FaultSchedule | None = None, on_sequence=None,
                 calibration: CalibrationBundle | None = None) -> CaptureResult:
    """Capture ``sequences`` repetitions of ``plan``'s illuminant sequence of ``scene`` on the twin.

    The camera runs at the plan's exposure, at the fastest frame rate the camera and the light's switch time allow
    (never faster than the rig description's rate); frames go through the driver, ring buffer and assembler like
    hardware frames.

    Parameters
    ----------
    description : RigDescription
    plan : Plan
    scene : specgpu.rig.scene.SpectralScene
        At the camera's resolution.
    sequences : int
        Number of whole sequences to expose (>= 1).
    noise_seed : int, optional
        Seed of the frames' temporal noise (the camera's fixed pattern comes from the description's seed).
    faults : FaultSchedule, optional
        Injected faults (none by default).
    on_sequence : callable, optional
        Given each complete sequence as it arrives (then sequences are not kept in the result).
    calibration : CalibrationBundle, optional
        The bundle the plan was made from: the rig's clock starts where that calibration ended plus the rig's
        ``capture_delay`` (so the lamp has drifted on as on a bench); without it, at ``capture_delay``.

    Returns
    -------
    CaptureResult
        The complete sequences (each with its (K, H, W) ``frames``) and the assembler's counters (``assembly``).

    Examples
    --------
    >>> from specgpu.calibration import oracle_calibration
    >>> from specgpu.planning import make_plan
    >>> from specgpu.rig import CameraParameters, RigDescription, colorchecker_scene
    >>> rig = RigDescription(camera=CameraParameters(roi_width=320, roi_height=240))
    >>> bundle = oracle_calibration(rig)
    >>> plan = make_plan("narrowband", bundle, step_nm=20.0)
    >>> from specgpu.pipeline import capture_plan
    >>> result = capture_plan(rig, plan, colorchecker_scene(240, 320), noise_seed=1, calibration=bundle)
    >>> result.sequences[0].frames.shape == (plan.K, 240, 320)
    True
    """
    if sequences < 1:
        raise ValueError(f"sequences must be >= 1, got {sequences}")
    check_scene_covers(scene, plan, description.light.line_fwhm_nm, rig=description)
    clock = description.capture_delay
    if calibration is not None:
        clock += float(calibration.reports.get("rig_clock_end_s", 0.0))
    rig = TwinRig(plan.rig_description(description), scene=scene, clock_start_s=clock)
    if noise_seed is not None:
        rig.seed = noise_seed
    driver = TwinDriver(rig, patterns=plan.patterns, n_frames=plan.K * sequences,
                        faults=faults or FaultSchedule(), pacing="free")
    return capture_sequences(driver, plan.K, on_sequence=on_sequence)


def check_scene_covers(scene, plan: Plan, slack_nm: float = 5.0, *, rig: RigDescription | None = None) -> None:
    """Refuse a scene whose bands do not cover the wavelengths the plan's illuminants light (above 1 % of their
    peak, less ``slack_nm``): its reflectance there would be made up, never measured. Given ``rig``, its
    ``[motion] object`` cube is held to the same test, named by the key and the rig file."""
    targets = np.asarray(plan.target_spectra, np.float64)
    lit = plan.light_wavelengths[targets.max(axis=0) > 0.01 * targets.max()]
    if lit.size == 0:
        return
    cubes = [(f"scene {scene.name!r}", scene.wavelengths)]
    obj = "" if rig is None else rig.motion.object
    if Path(obj).suffix.lower() in (".exr", ".npz", ".hdr"):  # a file (built-ins span the visible)
        cubes.append((f"{rig.source}: [motion] object {obj}", read_scene(obj).wavelengths))
    for what, wavelengths in cubes:
        lo, hi = float(wavelengths[0]), float(wavelengths[-1])
        if lo > lit[0] + slack_nm or hi < lit[-1] - slack_nm:
            raise ValueError(f"{what} covers {lo:g}-{hi:g} nm but the {plan.method} plan lights "
                             f"{lit[0]:g}-{lit[-1]:g} nm; give a cube whose bands cover its illuminants")


#: Written first into a sequence folder being captured and removed once ``sequence.json`` is written: a folder
#: holding it is an interrupted capture that the next capture into it may replace.
INCOMPLETE_MARKER = ".specgpu-capture-incomplete"


class CaptureWriter:
    """Write a capture into a sequence folder as its sequences arrive (a long capture never holds its frames in
    memory): copies of the plan and calibration first, each frame as it comes, ``sequence.json`` last.

    The folder must be new, empty, or an interrupted capture (it holds :data:`INCOMPLETE_MARKER`); one that holds a
    sequence, or files specgpu did not put there (a user's own ``plan.npz``), is refused before anything is written
    unless ``overwrite``.

    Nothing captured is lost: each complete sequence is journaled as it is written (:meth:`add`), so a capture
    killed outright leaves a folder :func:`salvage_capture` indexes; one stopped by an error or an interrupt after
    at least one complete sequence is closed with those sequences by :meth:`keep` (its ``sequence.json`` says it was
    cut short); :meth:`abort` removes what this writer wrote, for a capture that has nothing to keep.
    """

    def __init__(self, directory, plan_path, calibration_path, *, overwrite: bool = False):
        directory = self.directory = Path(directory)
        self.plan = load_plan(plan_path)
        check_capture_folder(directory, overwrite=overwrite)
        self._created = not directory.exists()
        directory.mkdir(parents=True, exist_ok=True)
        self.marker = directory / INCOMPLETE_MARKER
        (directory / "sequence.json").unlink(missing_ok=True)  # overwrite: never complete while rewritten
        self.marker.write_text(f"an interrupted specgpu capture (pid {os.getpid()}); `specgpu salvage` indexes "
                               "its complete sequences, a capture into this folder replaces it\n", encoding="utf-8")
        self._copies = []
        for source, name in ((plan_path, PLAN_FILE), (calibration_path, CALIBRATION_FILE)):
            with atomic_path(directory / name) as tmp:
                shutil.copyfile(source, tmp)
            self._copies.append(directory / name)
        self.frames = io.SequenceWriter(directory, self.plan.hash, overwrite=True,
                                        journal={"plan_method": self.plan.method, "K": self.plan.K})
        self.sequences = 0

    def add(self, sequence) -> None:
        """Write one complete sequence (a :class:`specgpu.capture.assemble.Sequence`) and journal it."""
        for frame, record in zip(sequence.frames, sequence.frame_records()):
            self.frames.add(frame, record)
        self.frames.commit()
        self.sequences += 1

    def keep(self, assembly, metadata=None, *, reason: str, requested: int | None = None) -> Path:
        """Close a capture cut short (``reason``: what stopped it) with the complete sequences written so far;
        the frames of a sequence it was writing are removed; ``assembly`` may be None (the counters died with
        the capture). ``sequence.json`` records ``interrupted`` (the reason) and ``sequences_requested``."""
        self.frames.truncate(self.sequences * self.plan.K)
        meta = {**(metadata or {}), "interrupted": reason}
        if requested is not None:
            meta["sequences_requested"] = int(requested)
        return self.close(assembly, meta)

    def close(self, assembly, metadata=None) -> Path:
        """Write ``sequence.json`` (with the assembler's counters) and remove the marker: the folder is complete."""
        if not self.sequences:
            raise ValueError(f"{self.directory}: no complete sequence was captured ({assembly.as_dict()})")
        meta = {"plan_method": self.plan.method, "K": self.plan.K, "sequences": self.sequences,
                "assembly": None if assembly is None else assembly.as_dict(), **(metadata or {})}
        self.frames.close(meta)
        self.marker.unlink(missing_ok=True)
        return self.directory

    def abort(self, error=None) -> None:
        """Remove the frames, copies and marker written (and the folder, when this writer created it); ``error``,
        what cut the capture short, is the caller's to report."""
        self.frames.abort()
        for path in (*self._copies, self.marker):
            path.unlink(missing_ok=True)
        if self._created:
            try:
                self.directory.rmdir()
            except OSError:
                pass


def salvage_capture(directory) -> dict:
    """Make a capture folder left by a killed capture (no ``sequence.json``, its journal present) readable: index
    every complete sequence whose journal lines and frames are intact (:func:`specgpu.io.journal.salvage_sequence`),
    keep the plan and calibration copies, remove the interrupted marker. Returns what was kept (``sequences``,
    ``frames_kept``, ``frames_journaled``, ``left_out``: each sequence not kept and why, ``kept_sequences``,
    ``stopped``). The motion truth of a capture on a moving twin is renumbered with the sequences
    (:func:`specgpu.pipeline.motion_record.renumber_truth`).

    Verify first, commit last: the plan copy must be the plan the journal names and match the calibration copy
    before anything is written; the index written must read back as a sequence folder before the journal is
    removed. A refusal leaves the folder as it was, to be salvaged again once fixed; no frame is deleted."""
    directory = Path(directory)
    if not directory.is_dir():
        raise FileNotFoundError(f"{directory}: capture folder not found")
    for name in (PLAN_FILE, CALIBRATION_FILE):
        if not (directory / name).is_file():
            raise FileNotFoundError(f"{directory}: {name} is missing; the capture was killed before it was copied, "
                                    "so its frames cannot be recovered with their plan")
    plan = load_plan(directory / PLAN_FILE)
    bundle = load_calibration(directory / CALIBRATION_FILE)

    def check(doc):
        if doc["plan_hash"] != plan.hash:
            raise ValueError(f"{directory / PLAN_FILE}: is plan {plan.hash[:12]} but the frames were captured with "
                             f"plan {str(doc['plan_hash'])[:12]} (the journal says so); put that plan's file back "
                             "and salvage again")
        plan.check_calibration(bundle, name=f"{directory / PLAN_FILE}")

    check(journal_header(directory))  # before the frames are grouped in sequences of the plan's length

    def confirm():  # the index reads back; then a moving capture's truth follows its sequences' new numbers
        salvaged = read_capture(directory).meta["metadata"]["salvaged"]
        renumber_truth(directory, salvaged["kept_sequences"])

    info = io.salvage_sequence(directory, plan.K, check=check, confirm=confirm)
    (directory / INCOMPLETE_MARKER).unlink(missing_ok=True)
    return info


def check_capture_folder(directory, *, overwrite: bool = False) -> None:
    """Refuse, in one line, a capture folder that is not new, empty or an interrupted capture."""
    directory = Path(directory)
    if not directory.exists():
        return
    if not directory.is_dir():
        raise ValueError(f"{directory}: exists and is not a folder")
    if overwrite:
        return
    if (directory / "sequence.json").exists():
        raise FileExistsError(f"{directory} already holds a sequence (sequence.json); choose another --out")
    if (directory / INCOMPLETE_MARKER).exists():
        return  # an interrupted capture: replaced
    others = sorted(p.name for p in directory.iterdir() if not p.name.startswith("."))
    if others:
        shown = ", ".join(others[:3]) + (f" and {len(others) - 3} more" if len(others) > 3 else "")
        raise FileExistsError(f"{directory} holds files a capture would overwrite or mix with ({shown}); "
                              "choose a new or empty folder")


def write_capture(directory: str | os.PathLike[str], sequences, assembly, plan_path: str | os.PathLike[str],
                  calibration_path, *, metadata: dict | None = None,
                  overwrite: bool = False) -> Path:
    """Write complete sequences (from :func:`capture_plan`) into a sequence folder with copies of the plan and
    calibration; ``assembly`` is the assembler's counters, kept in ``sequence.json``.

    The plan and calibration are copied first and ``sequence.json`` is written last, so an interrupted write
    never leaves a folder that reads as complete (see :class:`CaptureWriter`, which this uses).
    """
    directory = Path(directory)
    if not sequences:
        raise ValueError(f"{directory}: no complete sequence was captured ({assembly.as_dict()})")
    writer = CaptureWriter(directory, plan_path, calibration_path, overwrite=overwrite)
    try:
        for sequence in sequences:
            writer.add(sequence)
        return writer.close(assembly, metadata)
    except BaseException:
        writer.abort()
        raise


def default_basis(chart: str = EVALUATION_CHART):
    """The uncentred PCA basis of colour-science's measured reflectances with ``chart`` left out of training:
    every set holding the same patches, and any spectrum within 0.01 RMS of one of its patches."""
    _, chart_spectra = true_patch_spectra(colorchecker_scene(24, 36, chart=chart), DEFAULT_WAVELENGTHS)
    return pca_basis(load_reflectances(exclude=evaluation_exclusions(chart), exclude_similar_to=chart_spectra))


@dataclass
class SequenceFolder:
    """A sequence folder read back and checked: frames (S, K, H, W), the plan and calibration, records, meta."""

    path: Path
    frames: np.ndarray
    plan: Plan
    calibration: CalibrationBundle
    records: list
    meta: dict

    @property
    def sequences(self) -> int:
        return self.frames.shape[0]


def _zarr_not_a_sequence(directory: Path) -> str:
    """The refusal of a zarr recording where a sequence folder is read: say what it is and what reads it."""

    try:
        attrs = json.loads((directory / "zarr.json").read_text()).get("attributes", {})
    except (OSError, ValueError, AttributeError):
        attrs = {}
    if attrs.get("format") != "specgpu.recording":
        return f"{directory}: a zarr store, not a sequence folder (sequence.json); recover reads capture folders"
    if attrs.get("frames"):
        return (f"{directory}: a zarr recording, not a sequence folder; re-process its raw frames with "
                f"`specgpu batch {directory} --plan PLAN --out OUT.zarr` (recover reads capture folders)")
    return (f"{directory}: a zarr recording without raw frames, not a sequence folder; its results are in it "
            "(specgpu.io.recording.open_recording, or xarray.open_zarr), and recover reads capture folders")


def read_capture(directory: str | os.PathLike[str]) -> SequenceFolder:
    """Read a sequence folder; refuse it when the plan or calibration is missing or does not match its hashes,
    or when its frames are not whole sequences in pattern order.

    Parameters
    ----------
    directory : path
        A sequence folder written by ``specgpu capture`` (or :func:`write_capture`).

    Returns
    -------
    SequenceFolder
        Its frames (S, K, H, W), plan, calibration, frame records and metadata.

    Examples
    --------
    Two sequences of 7 Hadamard-coded frames, written as a capture folder and read back:

    >>> import tempfile
    >>> from pathlib import Path
    >>> from specgpu import calibration, pipeline, planning, rig
    >>> twin = rig.RigDescription(camera=rig.CameraParameters(roi_width=320, roi_height=240))
    >>> cal = calibration.oracle_calibration(twin)
    >>> root = Path(tempfile.mkdtemp())
    >>> codes = planning.make_plan("hadamard", cal, bands=7)
    >>> shot = pipeline.capture_plan(twin, codes, rig.natural_scene(240, 320), sequences=2, noise_seed=5,
    ...                              calibration=cal)
    >>> plan_file, cal_file = pipeline.save_plan_and_calibration(root, codes, cal)
    >>> folder = pipeline.write_capture(root / "capture", shot.sequences, shot.assembly, plan_file, cal_file)
    >>> pipeline.read_capture(folder).frames.shape
    (2, 7, 240, 320)
    """
    directory = Path(directory)
    _check_not_zarr(directory)
    _check_interrupted(directory)
    frames, records, meta = io.read_sequence(directory)
    plan, bundle = _capture_plan(directory, records, meta)
    return SequenceFolder(directory, frames.reshape(-1, plan.K, *frames.shape[1:]), plan, bundle, records, meta)


def read_capture_header(directory) -> tuple[list, dict, Plan, CalibrationBundle]:
    """What :func:`read_capture` checks, without reading a pixel: ``(records, meta, plan, calibration)`` of a
    sequence folder (``sequence.json`` validated, the plan and calibration matching it, whole sequences in pattern
    order). The frames are then read per sequence (:func:`specgpu.io.sequence.read_frames`), so a reader's memory does
    not grow with the capture."""
    directory = Path(directory)
    _check_not_zarr(directory)
    _check_interrupted(directory)
    records, meta = io.read_sequence_header(directory)
    plan, bundle = _capture_plan(directory, records, meta)
    return records, meta, plan, bundle


def _check_not_zarr(directory: Path) -> None:
    if (directory / "zarr.json").is_file() and not (directory / io.SEQUENCE_FILE).exists():
        raise ValueError(_zarr_not_a_sequence(directory))


def _check_interrupted(directory: Path) -> None:
    if (directory / INCOMPLETE_MARKER).exists() and not (directory / io.SEQUENCE_FILE).exists():
        salvage = (" `specgpu salvage DIR` indexes its complete sequences;"
                   if (directory / io.JOURNAL_FILE).exists() else "")
        raise ValueError(f"{directory}: an interrupted capture (no sequence.json);{salvage} capture again into it "
                         "to replace it, or delete it")


def _capture_plan(directory: Path, records, meta) -> tuple[Plan, CalibrationBundle]:
    """The plan and calibration stored in a sequence folder, checked against its ``sequence.json``."""
    for name in (PLAN_FILE, CALIBRATION_FILE):
        if not (directory / name).is_file():
            raise FileNotFoundError(f"{directory}: {name} is missing; capture with `specgpu capture` (it stores "
                                    "the plan and calibration beside the frames)")
    plan = load_plan(directory / PLAN_FILE)
    recorded = meta.get("plan_hash", "")
    if plan.hash != recorded:
        raise ValueError(f"{directory}: the frames were captured with plan {recorded[:12] or '(none)'} but "
                         f"{PLAN_FILE} is plan {plan.hash[:12]}")
    bundle = load_calibration(directory / CALIBRATION_FILE)
    plan.check_calibration(bundle, name=f"{directory / PLAN_FILE}")
    K = plan.K
    indices = np.array([r["pattern_index"] for r in records])
    if len(indices) % K or not np.array_equal(indices, np.tile(np.arange(K), len(indices) // K)):
        raise ValueError(f"{directory}: frames are not whole sequences of the plan's {K} patterns in order")
    return plan, bundle


def recover(folder: SequenceFolder, *, sequence: int | None = None, out_dtype=np.float32, device=None,
            white_roi=None, white_reflectance=None, motion: str = "none") -> np.ndarray:
    """The plan's outputs (H, W, B) from a sequence folder: one sequence, or the mean of all (``sequence=None``:
    averaging repeated sequences of a still scene lowers the temporal noise).

    A pixel where any frame used sits at the sensor's maximum code (saturated, flagged per sequence before any
    averaging) has no valid measurement: its outputs are NaN, never a clipped, wrong value.

    ``white_roi`` (``"X,Y,W,H"``) names a reference white of ``white_reflectance`` (a number or a CSV; 0.99 by
    default) in the field: each sequence's decoder is rescaled for the light's drift since calibration
    (:mod:`specgpu.planning.correction`): the colour change fitted once on the sequences' mean white gains (it drifts
    over hours; each frame's own power fluctuation averages down over the sequences), each sequence then rescaled by
    its own gains. A plan with an ambient frame (``plan --ambient``) has that frame subtracted
    instead of the calibration's dark level. Either way each sequence is decoded on its own, then averaged.

    Parameters
    ----------
    folder : SequenceFolder
        Frames, plan and calibration (:func:`read_capture`).
    sequence : int, optional
        The sequence to recover; None averages all.
    out_dtype : numpy dtype
        Storage of the result.
    device : optional
        OpenCL device selector.
    white_roi, white_reflectance : optional
        The reference white in the field, as above.
    motion : {"none", "global", "affine", "flow"}
        ``"global"``: the scene moved during the sequence; a translation per frame (``"affine"``: an affine map,
        for a rotation or zoom) is estimated and compensated in the decoding pass (:mod:`specgpu.pipeline.moving`), the
        outputs are the scene at the sequence's reference time, and pixels some frame saw outside the field are NaN.
        One sequence at a time (the scene moves between sequences too): ``sequence`` is required unless the folder
        holds one.

    Returns
    -------
    ndarray, (H, W, B)
        The plan's outputs on ``plan.output_wavelengths`` (reflectance, or XYZ for a tristimulus plan); NaN
        where saturated.

    Examples
    --------
    A white plate, captured on a small twin through 20 nm narrowband frames, recovers as a white plate:

    >>> from pathlib import Path
    >>> import numpy as np
    >>> from specgpu import calibration, pipeline, planning, rig
    >>> small = rig.RigDescription(camera=rig.CameraParameters(roi_width=320, roi_height=240))
    >>> cal = calibration.oracle_calibration(small)
    >>> bands = planning.make_plan("narrowband", cal, step_nm=20.0)
    >>> shot = pipeline.capture_plan(small, bands, rig.white_plate_scene(240, 320), noise_seed=3, calibration=cal)
    >>> cube = pipeline.recover(pipeline.SequenceFolder(Path("mem"), shot.sequences[0].frames[None], bands, cal,
    ...                                                 [], {}))
    >>> cube.shape[:2], bool(abs(np.nanmedian(cube) - 0.99) < 0.05)
    ((240, 320), True)
    """
    mode = check_motion_mode(motion)
    if mode != "none":
        return _recover_moving(folder, sequence, white_roi, out_dtype, device,
                               "translation" if mode == "global" else mode)
    if white_roi is not None or ambient_index(folder.plan) is not None:
        plan, bundle = folder.plan, folder.calibration
        picked, decoded = _sequence_decoders(folder, sequence, white_roi, white_reflectance)
        y, gain = None, live_gain(bundle.flat_field)
        for fr, dark, A in decoded:
            ys = np.asarray(apply_linear(fr, A, dark, gain, out_dtype=np.float32, device=device))
            y = ys if y is None else y + ys
        y = (y / len(picked)).astype(out_dtype)
        saturated = np.any(folder.frames[list(picked)] >= bundle.max_code, axis=(0, 1))
        if saturated.any():
            y[saturated] = np.nan
        return y
    if sequence is None:
        used = folder.frames
        frames = used.mean(axis=0, dtype=np.float32) if folder.sequences > 1 else used[0]
    else:
        if not 0 <= sequence < folder.sequences:
            raise ValueError(f"sequence {sequence} is out of range: {folder.path} holds {folder.sequences}")
        used = folder.frames[sequence:sequence + 1]
        frames = used[0]
    plan, bundle = folder.plan, folder.calibration
    ratio = bundle.flat_ratio(plan.patterns)
    if ratio is not None or bundle.reports.get("linearity_c_per_dn2", 0.0) > 0:
        frames = _flatten_by_wavelength(frames, bundle.dark_at(plan.exposure_s), ratio, bundle)
    y = apply_linear(frames, plan.A, bundle.dark_at(plan.exposure_s), live_gain(bundle.flat_field),
                     out_dtype=out_dtype, device=device)
    saturated = np.any(used >= bundle.max_code, axis=(0, 1))
    if saturated.any():
        y[saturated] = np.nan
    return y


def _recover_moving(folder: SequenceFolder, sequence, white_roi, out_dtype, device, model) -> np.ndarray:
    """:func:`recover` of one sequence of a moving scene (``motion="global"`` or ``"affine"``)."""
    if sequence is None:
        if folder.sequences != 1:
            raise ValueError(f"motion=global recovers one sequence at a time (the scene moves between sequences); "
                             f"{folder.path} holds {folder.sequences}: give the sequence (--sequence N)")
        sequence = 0
    if not 0 <= sequence < folder.sequences:
        raise ValueError(f"sequence {sequence} is out of range: {folder.path} holds {folder.sequences}")
    if white_roi is not None or ambient_index(folder.plan) is not None:
        raise ValueError("motion=global does not combine with a reference white or an ambient frame yet (both "
                         "assume the same pixels in every frame)")
    plan, bundle = folder.plan, folder.calibration
    frames = folder.frames[sequence]
    dark = bundle.dark_at(plan.exposure_s)
    ratio = bundle.flat_ratio(plan.patterns)
    if ratio is not None or bundle.reports.get("linearity_c_per_dn2", 0.0) > 0:
        frames = _flatten_by_wavelength(frames, dark, ratio, bundle)
    res = recover_moving(frames, plan.A, dark=dark, gain=bundle.flat_field, saturation=float(bundle.max_code),
                         model=model, device=device, reference_frames=reference_indices(plan),
                         residual=residual_check(plan, bundle))
    return res.y.astype(out_dtype, copy=False)


def _sequence_decoders(folder: SequenceFolder, sequence, white_roi, white_reflectance):
    """What :func:`recover` decodes each picked sequence with, when it decodes them one by one (a white ROI or an
    ambient frame): the picked indices and, per sequence, its corrected frames (linearised, per-pattern flat
    ratio), the level subtracted (the ambient frame or the calibration's dark) and its decoder."""
    plan, bundle = folder.plan, folder.calibration
    amb = ambient_index(plan)
    picked = range(folder.sequences) if sequence is None else [sequence]
    if sequence is not None and not 0 <= sequence < folder.sequences:
        raise ValueError(f"sequence {sequence} is out of range: {folder.path} holds {folder.sequences}")
    ratio = bundle.flat_ratio(plan.patterns)
    prepared = []
    for s in picked:
        fr = folder.frames[s]
        dark = fr[amb].astype(np.float32) if amb is not None else bundle.dark_at(plan.exposure_s)
        fr = _flatten_by_wavelength(fr, dark, ratio, bundle)
        gains = None if white_roi is None else white_gains(fr, plan, bundle, white_roi, white_reflectance,
                                                            dark=dark)
        prepared.append((fr, dark, gains))
    if white_roi is None:
        return picked, [(fr, dark, plan.A) for fr, dark, _ in prepared]
    # The light's colour drifts over hours: one colour fit on the sequences' mean gains (each frame's own power
    # fluctuation averages down), then each sequence's frames rescaled by its own gains.
    mean_gains = np.exp(np.mean([np.log(g) for _, _, g in prepared], axis=0))
    A_mean = corrected_decoder(plan, mean_gains, bundle, white_reflectance, sequences=len(prepared))
    return picked, [(fr, dark, A_mean / (gains / mean_gains)[None, :]) for fr, dark, gains in prepared]


def uncertainty(folder: SequenceFolder, *, sequence: int | None = None, illuminant: str | None = None,
                observer: str | None = None, device=None, white_roi=None, white_reflectance=None,
                integration: str = "rectangle") -> tuple[np.ndarray, np.ndarray | None]:
    """Per-pixel standard deviation (H, W, P) of :func:`recover`'s outputs for the same frames, options and
    corrections (white ROI, ambient frame, linearisation, per-pattern flat field) and, given an illuminant, the
    covariance (H, W, 3, 3) of their XYZ for ``observer`` (:mod:`specgpu.planning.uncertainty`); NaN where saturated."""
    used = folder.frames if sequence is None else folder.frames[sequence:sequence + 1]
    if sequence is not None and not 0 <= sequence < folder.sequences:
        raise ValueError(f"sequence {sequence} is out of range: {folder.path} holds {folder.sequences}")
    plan, bundle = folder.plan, folder.calibration
    gain = bundle.flat_field
    M = None if illuminant is None else plan.outputs_to_XYZ(illuminant, observer, integration)
    cov = None
    if white_roi is not None or ambient_index(plan) is not None:
        # decoded one sequence at a time by its own decoder: the variance of their mean is the sum of each
        # sequence's frame noise over S^2, plus what no frame shows (the prior's mismatch). A white reference's
        # gains rescale each sequence's decoder by its own frames' power, so the light's fluctuation is divided
        # out there; with the ambient frame alone it stays, at each frame's own signal above that frame. An
        # ambient frame brings its own noise, and the room light's shot noise in every frame.
        _, decoded = _sequence_decoders(folder, sequence, white_roi, white_reflectance)
        S = len(decoded)
        kw = {"light": white_roi is None, "device": device,
              "ambient_dark": None if ambient_index(plan) is None else bundle.dark_at(plan.exposure_s)}
        const = constant_covariance(plan)
        var = sum(frame_variance(fr, plan, dark, gain, A=A, **kw) for fr, dark, A in decoded) / S ** 2
        sigma = np.sqrt(np.maximum(var + np.diag(const).astype(np.float32), 0.0)).astype(np.float32)
        if M is not None:
            cov = sum(frame_covariance(fr, plan, dark, gain, M, A=A, **kw)
                      for fr, dark, A in decoded) / S ** 2 + M @ const @ M.T
    else:
        frames = used.mean(axis=0, dtype=np.float32) if used.shape[0] > 1 else used[0]
        dark = bundle.dark_at(plan.exposure_s)
        ratio = bundle.flat_ratio(plan.patterns)
        if ratio is not None or bundle.reports.get("linearity_c_per_dn2", 0.0) > 0:
            frames = _flatten_by_wavelength(frames, dark, ratio, bundle)  # as recover decodes them
        sigma = sigma_map(frames, plan, dark, gain, sequences=used.shape[0], device=device)
        if M is not None:
            cov = output_covariance(frames, plan, dark, gain, M, sequences=used.shape[0], device=device)
    saturated = np.any(used >= bundle.max_code, axis=(0, 1))
    if saturated.any():
        sigma[saturated] = np.nan
        if cov is not None:
            cov[saturated] = np.nan
    return sigma, cov


def dark_warning(folder: SequenceFolder, sequence: int | None = None) -> str | None:
    """One line saying why the dark level :func:`recover` subtracts from this capture cannot be trusted, or None.

    A plan with an ambient frame has its dark measured on the scene in every sequence: trusted. Otherwise the
    calibration's level at the plan's exposure is subtracted, and it is not trusted when: the calibration found
    light on the object with every mirror off (:attr:`CalibrationBundle.mirrors_off_light`: the white's share of it
    is subtracted from every darker object); the plan's exposure lies outside the exposures the calibration
    measured the dark level at; or more than 1 % of the pixels read, in some frame (mean of the sequences used),
    further below that level than the camera's noise allows (5 standard deviations of the dark level's temporal
    noise, from the plan's noise model, 1 DN without one, plus 0.5 DN).
    """
    plan, bundle = folder.plan, folder.calibration
    if ambient_index(plan) is not None:
        return None
    t = float(plan.exposure_s)
    reasons = []
    if bundle.mirrors_off_light:
        light = bundle.reports.get("mirrors_off_dn_per_s")
        amount = (f" ({float(light) * t * bundle.white_reflectance:.1f} DN on its white at {t * 1e3:.3g} ms)"
                  if isinstance(light, (int, float)) else "")
        reasons.append(f"the calibration found light with every mirror off{amount}")
    lo, hi = bundle.dark_range_s
    if not lo * (1 - 1e-6) <= t <= hi * (1 + 1e-6):
        reasons.append(f"the plan's exposure {t * 1e3:.3g} ms lies outside the {lo * 1e3:.3g}-{hi * 1e3:.3g} ms "
                       "the calibration measured its dark level at")
    used = folder.frames if sequence is None else folder.frames[sequence:sequence + 1]
    noise = plan.params.get("noise") if isinstance(plan.params, dict) else None
    var = noise.get("read_var_dn2") if isinstance(noise, dict) else None
    var = float(var) if isinstance(var, (int, float)) and np.isfinite(var) and var > 0 else 1.0
    margin = 5.0 * float(np.sqrt(var / used.shape[0])) + 0.5
    dark = bundle.dark_at(t)
    low = np.full(dark.shape, np.inf, np.float32)
    for k in range(used.shape[1]):
        np.minimum(low, used[:, k].mean(axis=0, dtype=np.float32) - dark, out=low)
    below = float(np.mean(low < -margin))
    if below > 0.01:
        reasons.append(f"{below:.1%} of the pixels read more than {margin:.1f} DN below that level")
    if not reasons:
        return None
    return (f"dark level not trusted ({bundle.dark_at(t).mean():.1f} DN subtracted, no ambient frame): "
            + "; ".join(reasons) + "; plan with --ambient")


def corrected_signal(frames, dark, ratio, bundle=None) -> np.ndarray:
    """(K, H, W) float32 signal above ``dark`` (one level per pixel), linearized (the sensor's compression measured
    by calibration) and multiplied by the per-pattern flat-field ratio (a calibration's wavelength-dependent flat
    field, :meth:`CalibrationBundle.flat_ratio`; None: 1): what :func:`recover` decodes."""
    f = np.asarray(frames, np.float32) - np.asarray(dark, np.float32)[None]
    if bundle is not None:
        f = np.asarray(bundle.linearize(f), np.float32)
    if ratio is not None:
        f *= ratio
    return f


def _flatten_by_wavelength(frames, dark, ratio, bundle=None) -> np.ndarray:
    """:func:`corrected_signal` with ``dark`` added back (frames for a linear map that subtracts it)."""
    f = corrected_signal(frames, dark, ratio, bundle)
    f += np.asarray(dark, np.float32)[None]
    return f


def to_XYZ(y: np.ndarray, plan: Plan, illuminant: str = "D65", *, observer: str | None = None,
           integration: str = "rectangle", device=None) -> np.ndarray:
    """XYZ (Y = 1 for the white) of a plan's outputs for ``observer`` (None: the plan's own for a tristimulus
    plan, else the 2 degree observer; :meth:`specgpu.planning.plans.Plan.resolve_observer`), reflectance integrated
    by ``integration`` (see :meth:`specgpu.planning.plans.Plan.outputs_to_XYZ`)."""
    observer = plan.resolve_observer(observer)
    plan.outputs_to_XYZ(illuminant, observer, integration)  # refuses outputs with no XYZ, or another light/observer
    if plan.output == "reflectance":  # the same weights, applied on the device
        return reflectance_to_XYZ(y, plan.output_wavelengths, illuminant=illuminant, cmfs=observer,
                                  integration=integration, device=device)
    return y  # a tristimulus plan's outputs are XYZ already


def to_Lab(XYZ: np.ndarray, plan: Plan, illuminant: str = "D65", *, observer: str | None = None,
           integration: str = "rectangle", device=None) -> np.ndarray:
    """CIELAB of :func:`to_XYZ`'s XYZ: its white is the plan's (:meth:`specgpu.planning.plans.Plan.white_XYZ`,
    the perfect diffuser integrated with the same weights), so a perfect white is (100, 0, 0)."""
    white = plan.white_XYZ(illuminant, plan.resolve_observer(observer), integration)
    return XYZ_to_Lab(XYZ, illuminant=white, device=device)


def save_plan_and_calibration(directory, plan: Plan, bundle: CalibrationBundle) -> tuple[Path, Path]:
    """Save a plan and its calibration into ``directory`` (the demo's report folder)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    calibration_path = directory / CALIBRATION_FILE
    plan_path = directory / f"plan-{plan.method}.npz"
    save_calibration(calibration_path, bundle)
    save_plan(plan_path, plan)
    return plan_path, calibration_path
