"""``specgpu plan``: a measurement plan (the illuminant sequence and its decoder) from a calibration bundle."""

from __future__ import annotations

import click
import numpy as np

from specgpu.apps.cli.options import RIG, Busy, Finite, command, lock, no_clash
from specgpu.calibration.bundle import load_calibration
from specgpu.core.validate import validate_method
from specgpu.pipeline.denoise import DENOISE_RADIUS
from specgpu.pipeline.projector import target_spectrum
from specgpu.pipeline.recovery import default_basis
from specgpu.planning import PLAN_METHODS, save_plan
from specgpu.planning.basis import load_basis
from specgpu.planning.correction import (
    ambient_needed,
    with_ambient_frame,
    with_drift_probes,
)
from specgpu.planning.reference_frames import reference_count, reference_indices, with_reference_frames
from specgpu.planning.requests import estimated_plan


def method_arguments(method, *, step_nm, bandwidth_nm, m, basis_path, exclude_chart, output_step_nm, illuminant,
                     observer, camera, spectrum):
    """The positional and keyword arguments of ``make_plan`` for METHOD, from the command's options."""
    if method in ("narrowband", "reciprocal"):
        return (), {"step_nm": step_nm, "bandwidth_nm": bandwidth_nm}
    if method in ("biased", "symmetric"):
        if basis_path:
            basis = load_basis(basis_path)
        else:
            with Busy("building the basis"):
                basis = default_basis(exclude_chart)
        return (basis,), {"m": m, "output_wavelengths": np.arange(400.0, 700.0 + 1e-9, output_step_nm)}
    if method == "tristimulus":
        return (), {"illuminant": illuminant, "cmfs": observer}
    if method == "camera":
        return (), {"camera": camera, "illuminant": illuminant}
    if method in ("optimal", "hadamard"):
        return (), {}
    sd = target_spectrum(spectrum)  # steady
    return (sd.values, sd.wavelengths), {}


def with_frames(plan, bundle, ambient, drift_probe, reference_every=None):
    """The plan with its drift probes and, where asked or where the calibration found light with every mirror
    off (said on stderr), an ambient frame; or, with ``reference_every``, its broadband reference frames (no
    ambient frame then: see :func:`added_frames`)."""
    if reference_every is not None:
        needed, why = ambient_needed(bundle)
        if ambient is None and needed:
            click.echo(f"no ambient frame with --reference-every although {why}: the two do not combine (for room "
                       "light on a moving scene: --ambient without --reference-every; recover --motion warps the "
                       "ambient frame)", err=True)
        return with_reference_frames(plan, bundle, reference_every)
    if drift_probe:
        plan = with_drift_probes(plan, bundle, sorted(drift_probe))
    needed, why = ambient_needed(bundle)
    if ambient is None and needed:
        ambient = True
        click.echo(f"adding an ambient frame: {why} (--no-ambient to leave it out)", err=True)
    elif ambient is False and needed:
        click.echo(f"Warning: no ambient frame although {why}: recover will subtract the white's all-off level "
                   "and read darker objects too dark", err=True)
    return with_ambient_frame(plan) if ambient else plan


def added_frames(bundle, ambient, drift_probe, reference_every=None):
    """Frames :func:`with_frames` will add to each sequence (so a time budget leaves room for them): a number, or
    with ``reference_every`` a callable of the plan's frames. Reference frames are refused in one line with an
    ambient frame or drift probes (see :func:`specgpu.planning.reference_frames.with_reference_frames`)."""
    if reference_every is not None:
        if ambient or drift_probe:
            raise click.UsageError("--reference-every does not combine with --ambient or --drift-probe: the probes "
                                   "serve a correction on fixed pixels, which the moving scene it is for moves "
                                   "across; --ambient alone serves a moving scene (recover --motion warps it)")
        return lambda frames: reference_count(frames, reference_every)
    return len(drift_probe) + int(bool(ambient) or (ambient is None and ambient_needed(bundle)[0]))


def summary(plan, digest, out):
    """The line ``specgpu plan`` prints: frames, exposure, frame period and sequence time, outputs, the file and
    the expected error."""
    expected = plan.params.get("expected", {})
    unit = "" if plan.output == "reflectance" else f" ({plan.output})"
    note = f"; expected RMSE{unit} {expected['rmse']:.4f} on the prior" if "rmse" in expected else ""
    if "rmse_at_decoder_noise" in expected and "denoise" in plan.params:
        note += (f" ({expected['rmse_at_decoder_noise']:.4f} where recover --denoise --denoise-radius "
                 f"{plan.params['denoise']['radius']} flattens the noise)")
    for key in ("dE2000", "dEab"):
        if key in expected:
            note += f", expected {key} {expected[key]:.3f} (RMS)"
    budget = plan.params.get("sequence_budget_s")
    within = f" (budget {budget * 1e3:g} ms)" if budget is not None else ""
    refs = len(reference_indices(plan))
    among = f" ({refs} broadband reference frames among them)" if refs else ""
    return (f"{plan.method}: {plan.K} frames{among} at {plan.exposure_s * 1e3:.2f} ms exposure, "
            f"{plan.frame_period_s * 1e3:.2f} ms frame period, {plan.sequence_s * 1e3:.1f} ms per sequence{within} "
            f"({1.0 / plan.sequence_s:.1f} sequences/s), {plan.A.shape[0]} outputs "
            f"({plan.output}); wrote {out} (plan {digest[:12]}, calibration {plan.calibration[:12]}){note}")


def budget_note(plan, sequence_ms) -> None:
    """Without ``--sequence-ms`` the optimal design takes the longest exposures that gain photons, seconds a
    sequence where a moving scene or a stream wants far less: say so on stderr, with the option that caps it."""
    if sequence_ms is None and plan.method == "optimal":
        click.echo(f"note: no --sequence-ms, so the optimal design exposes {plan.exposure_s * 1e3:.1f} ms a frame, "
                   f"{plan.sequence_s * 1e3:.0f} ms a sequence; --sequence-ms T designs within T ms a sequence",
                   err=True)


@command("plan")
@click.argument("method")
@click.option("--calib", required=True, type=click.Path(exists=True, dir_okay=False), help="Calibration bundle.")
@click.option("--out", required=True, type=click.Path(dir_okay=False), help="Plan to write (.npz).")
@click.option("--step-nm", type=Finite(min=0.1, max=300), default=10.0, show_default=True,
              help="Band spacing (narrowband, reciprocal).")
@click.option("--bandwidth-nm", type=Finite(min=0.1, max=300), default=None,
              help="Band width (narrowband, reciprocal; default the step).")
@click.option("--m", "m", type=int, default=5, show_default=True, help="Basis functions (biased, symmetric).")
@click.option("--basis", "basis_path", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Basis table (.npz); default: PCA of colour-science's reflectances without --exclude-chart.")
@click.option("--exclude-chart", default="ColorChecker N Ohta", show_default=True,
              help="Chart left out of the default basis training (the one you evaluate on).")
@click.option("--output-step-nm", type=Finite(min=0.1, max=300), default=10.0, show_default=True,
              help="Output wavelength spacing of basis methods (400-700 nm).")
@click.option("--illuminant", default="D65", show_default=True, help="Tristimulus / camera simulator illuminant.")
@click.option("--observer", default="CIE 1931 2 Degree Standard Observer", show_default=True,
              help="Tristimulus: the colour-matching functions (colour-science name) whose XYZ the plan recovers.")
@click.option("--camera", default="Nikon 5100 (NPL)", show_default=True, help="Camera simulator: sensitivities.")
@click.option("--spectrum", default="D65", show_default=True,
              help="Steady-state: target illuminant name (colour-science) for spectral rendering.")
@click.option("--estimator", type=click.Choice(["projection", "wiener", "smooth"], case_sensitive=False),
              default="projection", show_default=True,
              help="Decoder: the method's own, Wiener on the training prior, or smoothness-regularised LS.")
@click.option("--training", "training", multiple=True, type=click.Path(dir_okay=False),
              help="Training spectra (CSV, or .npz with wavelengths and reflectance) added to the default prior; "
                   "repeatable.")
@click.option("--smooth-nm", type=float, default=40.0, show_default=True,
              help="smooth estimator: correlation length of the smoothness prior, nm.")
@click.option("--training-only", is_flag=True, help="Use only --training files for the prior (no built-in sets).")
@click.option("--frames", type=click.IntRange(min=1, max=200), default=9, show_default=True,
              help="optimal: number of illuminants.")
@click.option("--objective", type=click.Choice(["rmse", "dE2000", "dEab"], case_sensitive=False), default="rmse",
              show_default=True, metavar="[rmse|dE2000|dEab]",
              help="optimal: the expected error minimised (colour differences under --illuminant).")
@click.option("--target", type=float, default=None, help="optimal: refuse a design whose expected error is above it.")
@click.option("--exposure-ms", type=float, default=None, help="optimal: expose at least this long (ms).")
@click.option("--sequence-ms", type=Finite(min=0.001, max=1e6), default=None,
              help="Design within this time per sequence (ms, every frame included): the exposure is capped so the "
                   "frames fit; the optimal design trades spectral shape against photons under the cap.")
@click.option("--denoise", is_flag=True,
              help="Design the decoder (and the optimal frames) for recover --denoise: for the shot and read noise "
                   "the guided filter leaves where the scene is flat (optimal, or --estimator wiener / smooth).")
@click.option("--denoise-radius", type=click.IntRange(min=1, max=64), default=DENOISE_RADIUS, show_default=True,
              help="With --denoise: the radius recover --denoise will filter with.")
@click.option("--bands", type=int, default=31, show_default=True, help="hadamard: bands (3, 7, 15, 31, 63).")
@click.option("--ambient/--no-ambient", default=None,
              help="Add an ambient frame (every mirror off) to each sequence; recover subtracts it (1 frame more). "
                   "Default: added where the calibration found light with every mirror off (room light, the DMD's "
                   "off-state) or could not tell.")
@click.option("--drift-probe", "drift_probe", type=float, multiple=True,
              help="Add a 20 nm drift probe band at NM to each sequence, read by recover --white-roi's colour fit "
                   "(1 frame more each; 430 and 650 let a 3-frame plan's drift correction hold). Repeatable.")
@click.option("--reference-every", "reference_every", type=click.IntRange(min=1), default=None, metavar="M",
              help="Add a broadband reference frame before the first frame and after every M frames (the decoder "
                   "does not read them; recover/stream/batch --motion registers them to each other instead of "
                   "the differently lit frames). More frames per sequence; no ambient frame or drift probes.")
@RIG
def plan_command(method, calib, out, step_nm, bandwidth_nm, m, basis_path, exclude_chart, output_step_nm,
                 illuminant, observer, camera, spectrum, estimator, training, training_only, frames, objective,
                 target, exposure_ms, sequence_ms, bands, rig_path, smooth_nm, ambient, drift_probe, denoise,
                 denoise_radius, reference_every):
    """Design a measurement plan: the illuminant sequence and its decoder.

    METHOD is one of: narrowband, reciprocal, biased, symmetric, tristimulus, camera, steady, optimal, hadamard.
    """
    validate_method(method, {k: k for k in (*PLAN_METHODS, "optimal", "hadamard")}, "METHOD")
    method = method.lower()
    no_clash([("--out", out)], [("--calib", calib), ("--basis", basis_path), ("--rig", rig_path),
                                ("--spectrum", spectrum), *(("--training", t) for t in training)])
    lock(out)
    bundle = load_calibration(calib)
    args, kwargs = method_arguments(method, step_nm=step_nm, bandwidth_nm=bandwidth_nm, m=m, basis_path=basis_path,
                                    exclude_chart=exclude_chart, output_step_nm=output_step_nm,
                                    illuminant=illuminant, observer=observer, camera=camera, spectrum=spectrum)
    plan = estimated_plan(method, bundle, args, kwargs, estimator.lower(), training, training_only, exclude_chart,
                          frames, objective, target, exposure_ms, bands, illuminant, output_step_nm, rig_path,
                          smooth_nm, progress=Busy, sequence_ms=sequence_ms,
                          extra_frames=added_frames(bundle, ambient, drift_probe, reference_every),
                          denoise_radius=denoise_radius if denoise else None)
    plan = with_frames(plan, bundle, ambient, drift_probe, reference_every)
    budget_note(plan, sequence_ms)
    click.echo(summary(plan, save_plan(out, plan), out))
