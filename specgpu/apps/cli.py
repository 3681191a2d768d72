"""The ``specgpu`` command.

Every command has --help, exits 0 on success and, on failure, prints one line saying why and exits non-zero.
"""

from __future__ import annotations

import sys

import click

from specgpu import __version__


def _one_line_usage(error: click.UsageError) -> click.UsageError:
    """A usage error as one ``Error: ...`` line (exit status 2): click prints a usage error with the command's
    synopsis and a "Try --help" line before it, three lines where every other error is one. The message keeps
    click's naming of the option or argument; the help pointer moves onto the same line."""
    if error.ctx is None or isinstance(error, getattr(click.exceptions, "NoArgsIsHelpError", ())):
        return error  # already one line (raised by a command), or the plain group's help (click >= 8.2)
    message = error.format_message().strip().splitlines()[0].rstrip().rstrip(".")
    hint = f"; see '{error.ctx.command_path} --help'" if error.ctx.command.get_help_option(error.ctx) else ""
    one = click.UsageError(message + hint)  # no context: click's show() then prints the Error: line alone
    one.__cause__ = error
    return one


class _Group(click.Group):
    """Turns any error a command raises into one line on stderr and exit status 1 (2 for usage errors)."""

    def make_context(self, info_name, args, parent=None, **extra):
        try:
            return super().make_context(info_name, args, parent=parent, **extra)
        except click.UsageError as error:  # the group's own options: `specgpu --bogus`
            raise _one_line_usage(error) from error

    def invoke(self, ctx):
        try:
            with _terminate_as_interrupt():
                return super().invoke(ctx)
        except click.UsageError as error:  # a command's options and arguments, an unknown command
            raise _one_line_usage(error) from error
        except (click.ClickException, click.exceptions.Exit, click.exceptions.Abort, SystemExit):
            raise
        except KeyboardInterrupt:
            click.echo("specgpu: interrupted", err=True)
            sys.exit(130)
        except Exception as error:  # noqa: BLE001 (the CLI promises one line, not a traceback)
            from specgpu.io.formats import final_names

            text = final_names(str(error)).strip()  # an output's name, never its temporary's
            message = text.splitlines()[0] if text else type(error).__name__
            raise click.ClickException(message) from error


class _terminate_as_interrupt:
    """SIGTERM (``kill``, a service manager stopping us) is handled like Ctrl-C: a stream drains, a capture or
    recover removes what it half wrote (a capture keeps its complete sequences); only ``kill -9`` cannot be
    handled, and a killed capture is salvaged (see README, Reliability)."""

    def __enter__(self):
        import signal
        import threading

        self._previous = None
        if threading.current_thread() is threading.main_thread():
            def interrupt(signum, frame):
                raise KeyboardInterrupt

            self._previous = signal.signal(signal.SIGTERM, interrupt)
        return self

    def __exit__(self, *exc):
        if self._previous is not None:
            import signal

            signal.signal(signal.SIGTERM, self._previous)


def _with_companions(named):
    """(option, path) pairs with each path's companion files (an ENVI header's data file) added after it."""
    from specgpu.io.files import companion_files

    out = []
    for opt, path in named:
        if path is None:
            continue
        out.append((opt, path))
        out += [(f"{opt}'s ENVI data file", c) for c in companion_files(path)]
    return out


def _no_clash(outputs, inputs=()):
    """Refuse (a usage error naming both options) two outputs that are one file, or an output that is an input:
    writing it would silently replace the other result or destroy the input. Companion files count: an ENVI
    header's data file is an input with its header, and an output written with it."""
    from specgpu.core.locks import same_path

    outputs = _with_companions(outputs)
    inputs = _with_companions(inputs)
    for i, (opt, path) in enumerate(outputs):
        for other, other_path in outputs[:i]:
            if same_path(path, other_path):
                raise click.UsageError(f"{other} and {opt} both name {path}; give each output its own file")
        for source, source_path in inputs:
            if same_path(path, source_path):
                raise click.UsageError(f"{opt} {path} is the input {source}; writing it would destroy that input, "
                                       "choose another file")


def _sequence_files(seq):
    """The files of a sequence folder a reader uses (its outputs must never land on them)."""
    from pathlib import Path

    from specgpu.io.files import SEQUENCE_FILE
    from specgpu.pipeline.recovery import CALIBRATION_FILE, PLAN_FILE

    folder = Path(seq)
    files = [(f"SEQ's {name}", folder / name) for name in (SEQUENCE_FILE, PLAN_FILE, CALIBRATION_FILE)]
    files += [(f"SEQ's {p.name}", p) for p in folder.glob("frame_*.tif")]
    return [("SEQ", folder), *files]


class _Staged:
    """Outputs written all or nothing: each to a temporary name beside its final one, renamed over the finals
    only once every one is written (with SIGINT / SIGTERM held back during the renames); on failure the temporaries
    are removed and the finals, old files included, are untouched."""

    def __init__(self):
        self.pairs = []  # (temporary, final), each output's companions before it
        self.outputs = []  # the finals asked for, in order

    def path(self, final):
        from specgpu.io.formats import new_temporary, write_target

        final = write_target(final)  # through a symbolic link, as a plain open() writes
        tmp = new_temporary(final)  # the mode a plain open() gives, not mkstemp's 0600
        self.pairs.append((tmp, final))
        return tmp

    def write(self, final, write, companions=()):
        """``write(path)`` to a temporary beside ``final``; an error names ``final``, never the temporary.
        ``companions``: suffixes of files the writer puts beside its path (an ENVI header's ``.img``), renamed with
        it, before it."""
        from pathlib import Path

        from specgpu.io.formats import final_names, write_target

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
        import signal

        from specgpu.io.formats import replace_with

        held = {signal.SIGINT, signal.SIGTERM}
        old = signal.pthread_sigmask(signal.SIG_BLOCK, held)
        try:
            for tmp, final in self.pairs:
                replace_with(tmp, final)  # a file replaced keeps its mode
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)
        return self.outputs


def _lock(*paths, folder: bool = False):
    """Hold the exclusive lock of these outputs until the command ends (a second writer refuses at once);
    ``folder``: output folders, whose missing parents are created. An output's companion files (an ENVI header's
    data file) are locked with it; every lock is on the resolved path (see :mod:`specgpu.core.locks`)."""
    from specgpu.core.locks import output_locks

    if not folder:
        paths = [p for _, p in _with_companions((None, p) for p in paths)]
    click.get_current_context().with_resource(output_locks(paths, make_parents=folder))


class _Finite(click.FloatRange):
    """A float in a range that is also finite (click's FloatRange lets NaN through every bound)."""

    def convert(self, value, param, ctx):
        import math

        rv = super().convert(value, param, ctx)
        if not math.isfinite(rv):
            self.fail(f"{value!r} is not a finite number.", param, ctx)
        return rv


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="specgpu")
def main():
    """specgpu: active-illumination spectral imaging on OpenCL (Tominaga and Horiuchi, JOSA A 2012)."""


@main.command()
@click.option("--device", "device", default=None, help="Device selector: 'P:D' indices or a name substring.")
@click.option("--devices", "devices_only", is_flag=True,
              help="List only the OpenCL devices, one a line: selector, name, type (* the one chosen).")
@click.option("--usb", is_flag=True,
              help="Also list the USB devices found, naming those specgpu drives (DLPC900 light, USB3 Vision "
                   "camera, Ocean spectrometer).")
def info(device, devices_only, usb):
    """OpenCL platforms and devices, the one chosen, and versions; --devices: the OpenCL devices alone; --usb:
    the USB devices too."""
    from specgpu.engine.runtime import describe, list_devices, select_device

    if devices_only:
        chosen = select_device(device)
        for d in list_devices():
            mark = "*" if d.device.int_ptr == chosen.int_ptr else " "
            click.echo(f"{mark} {d.selector}  {d.name.strip()}  [{d.type}, {d.platform.strip()}]")
    else:
        click.echo(describe(device))
    if usb:
        from specgpu.hardware.usb import list_usb_devices

        found = list_usb_devices()
        click.echo(f"USB devices: {len(found)}" + ("" if found else " (none)"))
        for dev in found:
            known = f"  <- {dev.description} ({dev.backend})" if dev.backend else ""
            click.echo(f"  {dev.vendor_id:04x}:{dev.product_id:04x} bus {dev.bus} address {dev.address}{known}")


@main.command()
@click.option("--device", "device", default=None, help="Device selector: 'P:D' indices or a name substring.")
@click.option("--verbose", "-v", is_flag=True, help="Print the error figures of every case.")
def selftest(device, verbose):
    """Run the kernel regression suite (golden set) on this machine's device; exit 1 if any kernel fails."""
    from specgpu.engine.selftest import run_selftest

    report = run_selftest(device=device)
    click.echo(report.format(verbose=verbose))
    if not report.passed:
        raise click.ClickException(f"selftest failed on {report.device}: {', '.join(report.failed_kernels())}")


@main.command()
@click.option("--device", "device", default=None, help="Device selector: 'P:D' indices or a name substring.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, writable=True), default=None,
              help="Also write the figures as JSON to this file.")
@click.option("--sizes", default="640x480,2048x2048", show_default=True,
              help="Comma-separated WxH image sizes.")
@click.option("--repeats", type=click.IntRange(min=1), default=None,
              help="Timed repetitions per case (default: by size).")
@click.option("--stream", "stream", is_flag=True,
              help="Benchmark the streaming pipeline instead (frames/s in, sequences/s out, latency, drops, CPU, "
                   "peak RSS) on a replayed twin recording.")
@click.option("--stream-size", default="640x480", show_default=True, help="With --stream: WxH of the frames.")
@click.option("--stream-seconds", type=click.FloatRange(min=0.5), default=10.0, show_default=True,
              help="With --stream: length of each sustained case.")
@click.option("--paced-seconds", type=click.FloatRange(min=0.5), default=60.0, show_default=True,
              help="With --stream: length of the case paced at the camera's 200 fps.")
@click.option("--stream-cases", default="fused,sigma,sigma_rms,white,cube,paced,overload,equality",
              show_default=True,
              help="With --stream: comma-separated cases to run (also dE_sigma).")
@click.option("--stream-rounds", type=click.IntRange(min=1), default=1, show_default=True,
              help="With --stream: interleaved rounds of the sustained cases (fused, sigma, sigma_rms, white, "
                   "dE_sigma); "
                   "each reports its median round.")
def bench(device, json_path, sizes, repeats, stream, stream_size, stream_seconds, paced_seconds, stream_cases,
          stream_rounds):
    """Throughput of each kernel against NumPy / colour-science baselines measured in the same run."""
    from specgpu.apps.bench import parse_sizes, run_bench

    if stream:
        from specgpu.apps.bench import run_stream_bench

        try:
            (width, height), = parse_sizes(stream_size)
        except ValueError as error:
            raise click.BadParameter(str(error), param_hint="--stream-size") from error
        cases = tuple(c.strip() for c in stream_cases.split(",") if c.strip())
        run_stream_bench(seconds=stream_seconds, paced_seconds=paced_seconds, overload_seconds=stream_seconds,
                         width=width, height=height, device=device, json_path=json_path, echo=click.echo,
                         cases=cases, rounds=stream_rounds)
        return
    try:
        parsed = parse_sizes(sizes)
    except ValueError as error:  # a usage error (exit 2) that names the bad token, before any device work
        raise click.BadParameter(str(error), param_hint="--sizes") from error
    run_bench(sizes=parsed, device=device, repeats=repeats, json_path=json_path, echo=click.echo)


# ------------------------------------------------------------------------------------------------ the main job

_RIG = click.option("--rig", "rig_path", type=click.Path(dir_okay=False), default=None,
                    help="Rig description TOML (default: the paper's rig, simulated by the digital twin).")
_PLAN = click.option("--plan", "plan_path", required=True, type=click.Path(exists=True, dir_okay=False),
                     help="Plan (specgpu plan).")
_SCENE = click.option("--scene", default=None, help="Scene: colorchecker, white, natural[:image], or a .exr / .npz "
                                                   "/ .hdr (ENVI) cube (default: the rig's [scene] source).")


def _resize_mode(ctx, param, value):
    from specgpu.rig.scene import validate_resize

    try:
        return validate_resize(value)
    except ValueError as error:
        raise click.BadParameter(str(error)) from None


_RESIZE = click.option(
    "--resize", default="scale", show_default=True, callback=_resize_mode, metavar="scale|exact|stretch|crop|pad",
    help="How a scene file of another size than the frame is fitted (nearest neighbour; what was done is printed "
         "and recorded): scale uniformly, refusing another aspect ratio; exact: refuse any resampling; stretch: "
         "each axis on its own (the aspect ratio changes); crop: scale to cover, centre-crop; pad: scale to fit, "
         "centre, black border.")


def _resampled(what, scene, meta=None, key="scene_resampled"):
    """Say on stderr (one line naming ``what``, e.g. '--scene s.npz') and in ``meta`` how a scene file was fitted
    to the frame; returns ``scene``."""
    if scene.resampled:
        from tqdm import tqdm

        # through tqdm: a line of its own even while a progress line is shown
        tqdm.write(f"specgpu: {what}: resampled {scene.resampled}", file=sys.stderr)
        if meta is not None:
            meta[key] = scene.resampled
    return scene


_ILLUMINANT = click.option(
    "--illuminant", default=None,
    help="Illuminant of XYZ, Lab and dE, recorded with every output [default: the plan's own for a tristimulus or "
         "camera plan, else D65]; another than a tristimulus or camera plan measures under is refused.")

_OBSERVER = click.option(
    "--observer", default=None,
    help="Observer (colour-matching functions) of XYZ, Lab and dE, recorded with every output [default: the plan's "
         "own for a tristimulus plan, else CIE 1931 2 Degree Standard Observer]; another than a tristimulus plan's "
         "is refused.")


def _hardware(description):
    """The rig's [hardware] table checked (None for the twin)."""
    if not description.hardware:
        return None
    from specgpu.hardware.rig import HardwareConfig

    return HardwareConfig.from_dict(description.hardware, source=description.source,
                                    base_dir=description.base_dir or None)


def _experiment(description, plan_path, calib, scene, resize="scale"):
    """The rig's calibration, a plan made from that calibration (stale: an error) and the scene at the camera's
    resolution (fitted by ``resize``, said on stderr): what capture and stream both start from."""
    from specgpu.calibration.bundle import load_calibration
    from specgpu.planning.plans import load_plan
    from specgpu.rig.scene import load_scene

    bundle = load_calibration(calib, rig=description)
    plan = load_plan(plan_path)
    plan.check_calibration(bundle, name=str(plan_path), calibration_name=str(calib))
    cam = description.camera
    truth = load_scene(scene or description.scene, cam.roi_height, cam.roi_width, resize=resize)
    return bundle, plan, _resampled(f"--scene {scene}" if scene else f"the rig's scene {description.scene}", truth)


class _Busy:
    """A progress line with elapsed time for a step of unknown length (tqdm, refreshed from a thread)."""

    def __init__(self, desc: str):
        import threading

        from tqdm import tqdm

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


@main.command()
@_RIG
@click.option("--out", required=True, type=click.Path(dir_okay=False), help="Calibration bundle to write (.npz).")
@click.option("--seed", type=click.IntRange(min=0, max=2**63 - 1), default=0, show_default=True,
              help="Seed of the twin's noise; on hardware, of the loops' perturbed start only.")
@click.option("--line-shape", type=click.Choice(["gaussian", "measured"]), default="gaussian", show_default=True,
              help="The light's line shape in the bundle: the design Gaussian, or tabulated per column from the "
                   "spectroradiometer's probe readings (no model of the slit).")
def calibrate(rig_path, out, seed, line_shape):
    """Run both feedback loops on the rig and write the calibration bundle."""
    from specgpu.calibration import calibrate as run, save_calibration
    from specgpu.rig.config import load_rig

    _no_clash([("--out", out)], [("--rig", rig_path)])
    description = load_rig(rig_path)
    hardware = _hardware(description)
    _lock(out)
    with _Busy("calibrating"):
        if hardware is None:
            bundle = run(description, seed=seed, line_shape=line_shape)
        else:  # real devices: the camera looks at the reference white, the spectrometer at the light's output
            from specgpu.hardware.rig import open_calibration_rig

            with open_calibration_rig(description, hardware=hardware) as rig:
                bundle = run(description, seed=seed, rig=rig, line_shape=line_shape)
    digest = save_calibration(out, bundle)
    reports = bundle.reports
    for loop, what in (("loop_a", "loop (a) camera + white"), ("loop_b", "loop (b) spectroradiometer")):
        if loop in reports:
            r = reports[loop]
            click.echo(f"{what}: {r['iterations']} iterations, residual {r['residual']:.4f} "
                       f"(tolerance {r['tolerance']:g}), converged {r['converged']}")
    click.echo(f"wrote {out} (calibration {digest[:12]})")


@main.command("plan")
@click.argument("method")
@click.option("--calib", required=True, type=click.Path(exists=True, dir_okay=False), help="Calibration bundle.")
@click.option("--out", required=True, type=click.Path(dir_okay=False), help="Plan to write (.npz).")
@click.option("--step-nm", type=_Finite(min=0.1, max=300), default=10.0, show_default=True,
              help="Band spacing (narrowband, reciprocal).")
@click.option("--bandwidth-nm", type=_Finite(min=0.1, max=300), default=None,
              help="Band width (narrowband, reciprocal; default the step).")
@click.option("--m", "m", type=int, default=5, show_default=True, help="Basis functions (biased, symmetric).")
@click.option("--basis", "basis_path", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Basis table (.npz); default: PCA of colour-science's reflectances without --exclude-chart.")
@click.option("--exclude-chart", default="ColorChecker N Ohta", show_default=True,
              help="Chart left out of the default basis training (the one you evaluate on).")
@click.option("--output-step-nm", type=_Finite(min=0.1, max=300), default=10.0, show_default=True,
              help="Output wavelength spacing of basis methods (400-700 nm).")
@click.option("--illuminant", default="D65", show_default=True, help="Tristimulus / camera simulator illuminant.")
@click.option("--observer", default="CIE 1931 2 Degree Standard Observer", show_default=True)
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
@click.option("--bands", type=int, default=31, show_default=True, help="hadamard: bands (3, 7, 15, 31, 63).")
@click.option("--ambient/--no-ambient", default=None,
              help="Add an ambient frame (every mirror off) to each sequence; recover subtracts it (1 frame more). "
                   "Default: added where the calibration found light with every mirror off (room light, the DMD's "
                   "off-state) or could not tell.")
@click.option("--drift-probe", "drift_probe", type=float, multiple=True,
              help="Add a 20 nm drift probe band at NM to each sequence, read by recover --white-roi's colour fit "
                   "(1 frame more each; 430 and 650 let a 3-frame plan's drift correction hold). Repeatable.")
@_RIG
def plan_command(method, calib, out, step_nm, bandwidth_nm, m, basis_path, exclude_chart, output_step_nm,
                 illuminant, observer, camera, spectrum, estimator, training, training_only, frames, objective,
                 target, exposure_ms, bands, rig_path, smooth_nm, ambient, drift_probe):
    """Design a measurement plan: the illuminant sequence and its decoder.

    METHOD is one of: narrowband, reciprocal, biased, symmetric, tristimulus, camera, steady, optimal, hadamard.
    """
    import numpy as np

    from specgpu.calibration.bundle import load_calibration
    from specgpu.planning.plans import PLAN_METHODS, save_plan
    from specgpu.core.validate import validate_method

    validate_method(method, {k: k for k in (*PLAN_METHODS, "optimal", "hadamard")}, "METHOD")
    method = method.lower()
    _no_clash([("--out", out)],
              [("--calib", calib), ("--basis", basis_path)] + [("--training", t) for t in training])
    _lock(out)
    bundle = load_calibration(calib)
    if method in ("narrowband", "reciprocal"):
        kwargs = {"step_nm": step_nm, "bandwidth_nm": bandwidth_nm}
        args = ()
    elif method in ("biased", "symmetric"):
        if basis_path:
            from specgpu.planning.basis import load_basis

            basis = load_basis(basis_path)
        else:
            from specgpu.pipeline.recovery import default_basis

            with _Busy("building the basis"):
                basis = default_basis(exclude_chart)
        args = (basis,)
        kwargs = {"m": m, "output_wavelengths": np.arange(400.0, 700.0 + 1e-9, output_step_nm)}
    elif method == "tristimulus":
        args, kwargs = (), {"illuminant": illuminant, "cmfs": observer}
    elif method == "camera":
        args, kwargs = (), {"camera": camera, "illuminant": illuminant}
    elif method in ("optimal", "hadamard"):
        args, kwargs = (), {}
    else:  # steady
        from specgpu.pipeline.projector import target_spectrum

        sd = target_spectrum(spectrum)
        args, kwargs = (sd.values, sd.wavelengths), {}
    plan = _estimated_plan(method, bundle, args, kwargs, estimator.lower(), training, training_only, exclude_chart,
                           frames, objective, target, exposure_ms, bands, illuminant, output_step_nm, rig_path,
                           smooth_nm)
    if drift_probe:
        from specgpu.planning.correction import with_drift_probes

        plan = with_drift_probes(plan, bundle, sorted(drift_probe))
    from specgpu.planning.correction import ambient_needed, with_ambient_frame

    needed, why = ambient_needed(bundle)
    if ambient is None and needed:
        ambient = True
        click.echo(f"adding an ambient frame: {why} (--no-ambient to leave it out)", err=True)
    elif ambient is False and needed:
        click.echo(f"Warning: no ambient frame although {why}: recover will subtract the white's all-off level "
                   "and read darker objects too dark", err=True)
    if ambient:
        plan = with_ambient_frame(plan)
    digest = save_plan(out, plan)
    expected = plan.params.get("expected", {})
    unit = "" if plan.output == "reflectance" else f" ({plan.output})"
    note = f"; expected RMSE{unit} {expected['rmse']:.4f} on the prior" if "rmse" in expected else ""
    for key in ("dE2000", "dEab"):
        if key in expected:
            note += f", expected {key} {expected[key]:.3f} (RMS)"
    click.echo(f"{plan.method}: {plan.K} frames at {plan.exposure_s * 1e3:.2f} ms, {plan.A.shape[0]} outputs "
               f"({plan.output}); wrote {out} (plan {digest[:12]}, calibration {plan.calibration[:12]}){note}")


def _estimated_plan(method, bundle, args, kwargs, estimator, training, training_only, exclude_chart, frames,
                    objective, target, exposure_ms, bands, illuminant, output_step_nm, rig_path, smooth_nm=40.0):
    """The plan of METHOD with the chosen decoder, the camera's noise model and its expected error recorded."""
    import numpy as np

    from specgpu.calibration.bundle import rig_fingerprint
    from specgpu.planning.design import plan_hadamard, plan_optimal
    from specgpu.planning.estimators import NoiseModel, default_prior, with_estimator
    from specgpu.planning.plans import make_plan
    from specgpu.rig.config import load_rig

    description = load_rig(rig_path)
    plain = method not in ("optimal", "hadamard") and estimator == "projection" and not training
    if plain and rig_path is None and bundle.rig and bundle.rig != rig_fingerprint(description):
        return make_plan(method, bundle, *args, **kwargs)  # no --rig for a custom rig's camera: no noise model
    if bundle.rig and bundle.rig != rig_fingerprint(description):
        raise ValueError(f"{'--rig ' + str(rig_path) if rig_path else 'the default rig'} is not the rig the "
                         "calibration was made on: give that rig's description with --rig (its camera's noise "
                         "model is needed)")

    def noise_at(t):
        return NoiseModel.from_rig(description, t)

    prior = None
    if method == "optimal" or estimator == "wiener" or training or training_only:
        with _Busy("building the training prior"):
            prior = default_prior(exclude_chart, training_files=training, builtin=not training_only)
    if method == "optimal":
        tr = None
        if objective.lower() != "rmse":
            from specgpu.planning.estimators import training_spectra

            tr = training_spectra(exclude_chart, prior.wavelengths, training_files=training,
                                  builtin=not training_only)
        with _Busy(f"designing {frames} illuminants"):
            return plan_optimal(bundle, prior, noise_at, frames=frames, objective=objective, illuminant=illuminant,
                                training=tr, output_wavelengths=np.arange(400.0, 700.0 + 1e-9, output_step_nm),
                                target=target, exposure_s=None if exposure_ms is None else exposure_ms / 1e3)
    plan = plan_hadamard(bundle, bands=bands) if method == "hadamard" else make_plan(method, bundle, *args, **kwargs)
    return with_estimator(plan, bundle, estimator, prior=prior, noise=noise_at(plan.exposure_s),
                          correlation_nm=smooth_nm)


@main.command()
@_RIG
@_PLAN
@click.option("--calib", required=True, type=click.Path(exists=True, dir_okay=False),
              help="The calibration the plan was made from (stored with the frames for recovery).")
@_SCENE
@click.option("--out", required=True, type=click.Path(file_okay=False),
              help="Sequence folder to write; a name ending in .zarr writes a zarr recording of the raw frames "
                   "instead (for specgpu batch).")
@click.option("--sequences", type=click.IntRange(min=1), default=1, show_default=True)
@click.option("--seed", type=click.IntRange(min=0, max=2**63 - 1), default=None,
              help="Seed of the frames' temporal noise.")
@_RESIZE
def capture(rig_path, plan_path, calib, scene, out, sequences, seed, resize):
    """Capture sequences of a plan on the rig (the twin by default) into a sequence folder."""
    from tqdm import tqdm

    from specgpu.pipeline.recovery import CaptureWriter, check_capture_folder
    from specgpu.rig.config import load_rig

    description = load_rig(rig_path)
    hardware = _hardware(description)  # a typo in [hardware] first, before any device or file work
    bundle, plan, truth = _experiment(description, plan_path, calib, scene, resize)
    cam = description.camera
    meta = {"scene": truth.name, "rig": rig_path or "<paper defaults>",
            **({"scene_resampled": truth.resampled} if truth.resampled else {})}
    if str(out).lower().rstrip("/").endswith(".zarr"):  # raw frames straight to disk, one chunk per sequence
        from specgpu.io.recording import refuse_existing

        _lock(out, folder=True)  # first: a killed capture's stale lock is cleared even when out is refused
        refuse_existing(out)
        writer = _ZarrCapture(out, plan, plan_path, calib, sequences, plan.K * cam.roi_height * cam.roi_width * 2,
                              meta)
    else:
        check_capture_folder(out)  # a folder holding a sequence or someone's files: refused before the capture
        _lock(out, folder=True)
        writer = CaptureWriter(out, plan_path, calib)  # frames go to disk as they come, never all held in memory
    try:
        with tqdm(total=sequences, desc="capturing", unit="seq", leave=False, file=sys.stderr) as bar:
            result = _capture_into(writer, bar, description, hardware, plan, bundle, truth, sequences, seed)
        writer.close(result.assembly, metadata=meta)
    except BaseException as error:
        _keep_or_abort(writer, error, out, sequences, meta)
        raise
    a = result.assembly
    click.echo(f"{writer.sequences} sequences of {plan.K} frames ({truth.name}, {cam.roi_width} x "
               f"{cam.roi_height}); dropped {a.dropped}, duplicated {a.duplicates}, missed triggers "
               f"{a.missed_triggers}, discarded {a.sequences_discarded}; wrote {out}")


def _keep_or_abort(writer, error, out, requested, meta) -> None:
    """A capture stopped by ``error``: keep the complete sequences already on disk (a folder is closed with them,
    marked interrupted; a zarr recording keeps what it committed) and say so on stderr; with none, remove what was
    written."""
    reason = "interrupted" if isinstance(error, KeyboardInterrupt) else f"{type(error).__name__}: {error}"
    kept = writer.sequences
    if not kept:
        writer.abort(error)
        return
    try:
        writer.keep(None, meta, reason=reason, requested=requested)
    except Exception as failed:  # noqa: BLE001 (the first error is the one raised; this one is reported)
        click.echo(f"specgpu: {kept} complete sequences are on disk in {out} but could not be indexed "
                   f"({failed}); `specgpu salvage {out}` indexes them", err=True)
        return
    click.echo(f"specgpu: capture stopped ({reason.splitlines()[0] if reason else ''}); kept {kept} of {requested} "
               f"sequences in {out}", err=True)


class _ZarrCapture:
    """``capture --out SEQ.zarr``: each complete sequence's raw frames committed to a zarr recording as it arrives
    (what was committed stays readable if the capture is cut short); the writer interface of CaptureWriter."""

    def __init__(self, out, plan, plan_path, calib, sequences, sequence_bytes, metadata):
        import shutil
        from pathlib import Path

        from specgpu.io.recording import ZarrRecorder, check_free_space

        check_free_space(out, sequences * (sequence_bytes + 4096),
                         what=f"the recording ({sequences} sequences of {plan.K} raw frames)")
        self.recorder = ZarrRecorder(out, plan, outputs=(), frames=True, metadata=metadata)
        shutil.copyfile(plan_path, Path(out) / "plan.npz")
        shutil.copyfile(calib, Path(out) / "calibration.npz")

    @property
    def sequences(self) -> int:
        return self.recorder.committed

    def add(self, sequence) -> None:
        from specgpu.pipeline import StreamResult

        self.recorder.write(StreamResult(self.recorder.committed, sequence.cycle, sequence.frame_ids,
                                         sequence.timestamps_s, {}, 0.0, frames=sequence.frames))

    def close(self, assembly, metadata=None) -> None:
        self.recorder.close()

    def abort(self, error=None) -> None:
        self.recorder.failed = self.recorder.failed or f"{type(error).__name__}: {error}"
        self.recorder.close()

    def keep(self, assembly, metadata=None, *, reason: str, requested: int | None = None) -> None:
        """A capture cut short: the committed sequences stay (each was committed as it arrived)."""
        self.recorder.failed = self.recorder.failed or reason
        self.recorder.close()


def _capture_into(writer, bar, description, hardware, plan, bundle, truth, sequences, seed):
    """Capture on the twin or the rig's devices, each complete sequence written as it arrives."""
    from specgpu.pipeline.recovery import capture_plan

    def keep(sequence):
        writer.add(sequence)
        bar.update()

    if hardware is None:
        result = capture_plan(description, plan, truth, sequences=sequences, noise_seed=seed, on_sequence=keep,
                              calibration=bundle)
    else:  # real devices: the same ring buffer and assembler, the plan uploaded to the light
        from specgpu.capture.session import capture_sequences
        from specgpu.hardware.rig import open_hardware

        driver = open_hardware(description, hardware=hardware, patterns=plan.patterns, calibration=bundle,
                               n_frames=plan.K * sequences, exposure_s=plan.exposure_s)
        try:
            result = capture_sequences(driver, plan.K, on_sequence=keep)
        finally:
            driver.close()
    return result


class _one_interrupt:
    """While a stream drains after Ctrl-C (or SIGTERM), further ones are reported, not obeyed: a second Ctrl-C
    would abandon the drain and lose what was captured. ``kill -9`` still stops it at once."""

    def __enter__(self):
        import signal
        import threading

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
        import signal

        for sig, previous in self._previous.items():
            signal.signal(sig, previous)


def _parse_reference(text, height, width, illuminant, resize="scale", meta=None, observer=None):
    """--delta-e-ref: an 'L,a,b' colour, or a scene (built-in name, cube file, or a loaded scene) whose Lab (under
    ``illuminant`` for ``observer``, None: the 2 degree observer) is the reference; a scene file of another size is
    fitted by ``resize``, said on stderr and in ``meta``."""
    import numpy as np

    from specgpu.rig.scene import SpectralScene

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
    from specgpu.engine.colorimetry import XYZ_to_Lab
    from specgpu.pipeline.evaluate import scene_XYZ
    from specgpu.rig.scene import load_scene
    from specgpu.core.spectra import DEFAULT_CMFS

    scene = load_scene(text, height, width, resize=resize)
    if not isinstance(text, SpectralScene):
        _resampled(f"--delta-e-ref {text}", scene, meta, "reference_resampled")
    observer = observer or DEFAULT_CMFS
    return XYZ_to_Lab(scene_XYZ(scene, illuminant, observer), illuminant, observer=observer)


@main.command()
@click.argument("seq", type=click.Path(exists=True, file_okay=False))
def salvage(seq):
    """Index the complete sequences of a capture folder whose capture was killed (kill -9, a crash, power loss).

    Each sequence a capture writes is journaled as it arrives; this checks every journal line and journaled frame
    against its checksum and writes sequence.json for every complete, intact sequence (marked salvaged, with the
    sequences left out and why). No frame is deleted, and the journal only once the index reads back: a refused
    salvage can be run again.
    """
    from specgpu.pipeline.recovery import salvage_capture

    _lock(seq, folder=True)  # not while a capture is still writing into it
    info = salvage_capture(seq)
    for gone in info["left_out"]:
        click.echo(f"specgpu: sequence {gone['sequence']} ({gone['first_file']} to {gone['last_file']}) left out: "
                   f"{gone['reason']}", err=True)
    rest = (f"; left out {len(info['left_out'])} of {info['sequences_journaled']} journaled sequences (listed "
            "above and in sequence.json)" if info["left_out"] else "")
    if info["frames_unindexed"]:
        rest += f"; {info['frames_unindexed']} frame file(s) outside the index left in place"
    click.echo(f"salvaged {info['sequences']} sequences ({info['frames_kept']} of {info['frames_journaled']} "
               f"journaled frames) in {seq}{rest}")


@main.command()
@click.argument("seq", type=click.Path(exists=True, file_okay=False))
@click.option("--out", required=True, type=click.Path(dir_okay=False),
              help="Recovered cube (.exr / .npz / .hdr ENVI); an XYZ map for a tristimulus plan.")
@click.option("--interleave", type=click.Choice(["bsq", "bil", "bip"]), default="bsq", show_default=True,
              help="ENVI (.hdr) cube layout: band sequential, interleaved by line or by pixel.")
@click.option("--xyz", "xyz_path", type=click.Path(dir_okay=False), default=None, help="Also write XYZ (EXR).")
@click.option("--lab", "lab_path", type=click.Path(dir_okay=False), default=None, help="Also write CIELAB (EXR).")
@click.option("--delta-e-ref", "ref", default=None,
              help="Reference: 'L,a,b', or a scene whose true colour per pixel (over all its bands) is it.")
@click.option("--delta-e", "de_path", type=click.Path(dir_okay=False), default=None,
              help="Colour-difference map to write (EXR; .png for a heat map).")
@click.option("--method", default="CIE 2000", show_default=True, help="CIE 1976, CIE 1994 or CIE 2000.")
@_ILLUMINANT
@_OBSERVER
@click.option("--sequence", type=int, default=None, help="Recover one sequence (default: the mean of all).")
@click.option("--half", is_flag=True, help="Write the cube in half precision.")
@click.option("--sigma", "sigma_path", type=click.Path(dir_okay=False), default=None,
              help="Also write the per-pixel standard deviation of each output and their RMS (EXR).")
@click.option("--delta-e-sigma", "de_sigma_path", type=click.Path(dir_okay=False), default=None,
              help="Also write the per-pixel dE2000 standard deviation (first-order, under --illuminant; EXR).")
@click.option("--device", "device", default=None, help="OpenCL device selector.")
@click.option("--white-roi", default=None, metavar="X,Y,W,H",
              help="A reference white in the field: rescale each sequence's decoder for the light's drift.")
@click.option("--white-reflectance", default=None, metavar="VALUE|CSV",
              help="Reflectance of the --white-roi white: a number or a CSV (wavelength nm, value). [0.99]")
@_RESIZE
def recover(seq, out, interleave, xyz_path, lab_path, ref, de_path, method, illuminant, observer, sequence, half,
            sigma_path, de_sigma_path, device, white_roi, white_reflectance, resize):
    """Recover a sequence folder: the cube and, when asked, XYZ, Lab and dE maps (written only if all succeed)."""
    from pathlib import Path

    import numpy as np

    from specgpu import io
    from specgpu.engine.colorimetry import DELTA_E_METHODS, delta_E
    from specgpu.pipeline.recovery import read_capture, recover as run, to_Lab, to_XYZ
    from specgpu.core.validate import validate_method

    if (ref is None) != (de_path is None):
        raise click.UsageError("--delta-e-ref and --delta-e go together")
    method = validate_method(method, DELTA_E_METHODS)
    outputs = [("--out", out), ("--xyz", xyz_path), ("--lab", lab_path), ("--delta-e", de_path),
               ("--sigma", sigma_path), ("--delta-e-sigma", de_sigma_path)]
    _no_clash(outputs, _sequence_files(seq) + ([("--delta-e-ref", ref)] if ref and Path(ref).exists() else []))
    _lock(*(p for _, p in outputs if p))  # before the work: a missing folder or a busy output is refused now
    folder = read_capture(seq)
    plan = folder.plan
    illuminant = plan.resolve_illuminant(illuminant, name=f"the plan of {seq}")
    observer = plan.resolve_observer(observer, name=f"the plan of {seq}")
    with _Busy("recovering"):
        if white_reflectance is not None and white_roi is None:
            raise click.UsageError("--white-reflectance needs --white-roi")
        try:
            y = run(folder, sequence=sequence, device=device, white_roi=white_roi, white_reflectance=white_reflectance)
        except ValueError as error:
            raise click.ClickException(str(error)) from None
        from specgpu.pipeline.recovery import dark_warning

        untrusted = dark_warning(folder, sequence)  # said once the spinner has gone, recorded with every output
        height, width = y.shape[:2]
        meta = {"plan_method": plan.method, "projections": plan.K, "plan_hash": plan.hash,
                "calibration": plan.calibration, "sequence_folder": str(seq),
                "sequences_averaged": 1 if sequence is not None else folder.sequences, "illuminant": illuminant,
                "observer": observer,
                **({"white_roi": white_roi, "white_reflectance": white_reflectance or 0.99} if white_roi else {}),
                **({"reflectance_scale_uncertainty": folder.calibration.reports["white_reflectance_uncertainty"]}
                   if "white_reflectance_uncertainty" in folder.calibration.reports else {}),
                **({"dark_untrusted": untrusted} if untrusted else {})}
        writes = []  # (final path, write(to path))
        if plan.output == "reflectance":
            if Path(out).suffix.lower() == ".hdr":  # ENVI: the .img data file renamed with its header
                writes.append((out, lambda p: io.write_cube(p, y, plan.output_wavelengths, half=half, metadata=meta,
                                                           interleave=interleave), (".img",)))
            else:
                writes.append((out, lambda p: io.write_cube(p, y, plan.output_wavelengths, half=half,
                                                           metadata=meta)))
        else:
            kind = "XYZ" if plan.output == "XYZ" else tuple(plan.output_labels)
            # kind bound now: the dE branch below reuses the name (a late-bound lambda wrote XYZ as a dE map)
            writes.append((out, lambda p, kind=kind: io.write_map(p, y, kind, half=half, metadata=meta)))
        XYZ = Lab = None
        if xyz_path or lab_path or de_path:
            XYZ = to_XYZ(y, plan, illuminant, observer=observer, device=device)
            Lab = to_Lab(XYZ, illuminant, observer=observer, device=device)
        if xyz_path:
            writes.append((xyz_path, lambda p: io.write_map(p, XYZ, "XYZ", metadata=meta)))
        if lab_path:
            writes.append((lab_path, lambda p: io.write_map(p, Lab, "Lab", metadata=meta)))
        if sigma_path or de_sigma_path:
            _sigma_writes(writes, folder, sequence, (illuminant, observer), sigma_path, de_sigma_path, XYZ, y,
                          meta, device, white_roi, white_reflectance)
        if de_path:
            dE = delta_E(_parse_reference(ref, height, width, illuminant, resize, meta, observer), Lab, method,
                         device=device)
            if Path(de_path).suffix.lower() == ".png":
                writes.append((de_path, lambda p: io.write_delta_E_png(p, dE, metadata=meta)))
            else:
                kind = {"CIE 1976": "dE76", "CIE 1994": "dE94", "CIE 2000": "dE2000"}[method]
                writes.append((de_path, lambda p, kind=kind: io.write_map(p, dE, kind, metadata=meta)))
    if untrusted:
        click.echo(f"Warning: {untrusted}", err=True)
    staged = _Staged()  # all or nothing: no output replaced until every one is written
    try:
        for final, write, *companions in writes:
            staged.write(final, write, *companions)
        written = staged.commit()
    except BaseException:
        staged.discard()
        raise
    saturated = int(np.isnan(y[..., 0]).sum())
    note = f"; {saturated} saturated pixels left NaN" if saturated else ""
    click.echo(f"{plan.method}: {plan.K} projections, {folder.sequences} sequences in {seq}; wrote "
               + ", ".join(str(p) for p in written) + note)


def _sigma_writes(writes, folder, sequence, colours, sigma_path, de_sigma_path, XYZ, y, meta, device,
                  white_roi=None, white_reflectance=None):
    """--sigma / --delta-e-sigma: the uncertainty maps of the recovery, appended to the writes; ``colours``: the
    (illuminant, observer) of the XYZ."""
    import numpy as np

    from specgpu import io
    from specgpu.planning.estimators import delta_E_sigma
    from specgpu.pipeline.recovery import to_XYZ, uncertainty

    illuminant, observer = colours
    sigma, cov = uncertainty(folder, sequence=sequence, illuminant=illuminant if de_sigma_path else None,
                             observer=observer, device=device, white_roi=white_roi, white_reflectance=white_reflectance)
    plan = folder.plan
    if sigma_path:
        rms = np.sqrt(np.mean(sigma.astype(np.float64) ** 2, axis=-1, keepdims=True)).astype(np.float32)
        names = [f"sigma_{label}" for label in plan.output_labels] + ["sigma_rms"]
        sig = np.concatenate([sigma, rms], axis=-1)
        writes.append((sigma_path, lambda p: io.write_map(p, sig, names, metadata=meta)))
    if de_sigma_path:
        xyz = XYZ if XYZ is not None else to_XYZ(y, plan, illuminant, observer=observer, device=device)
        des = delta_E_sigma(np.nan_to_num(xyz), np.nan_to_num(cov), illuminant, observer)
        des[~np.isfinite(xyz).all(axis=-1)] = np.nan
        writes.append((de_sigma_path, lambda p: io.write_map(p, des, ["dE2000_sigma"], metadata=meta)))


#: the longest stream: a year (a longer one overflows the sequence count the free-space check works out)
_MAX_STREAM_S = 366 * 86400


@main.command("stream")
@_RIG
@_PLAN
@click.option("--calib", required=True, type=click.Path(exists=True, dir_okay=False),
              help="The calibration the plan was made from.")
@_SCENE
@click.option("--seconds", type=_Finite(min=0, min_open=True, max=_MAX_STREAM_S), required=True,
              help="Capture time (at most a year: 31622400 s).")
@click.option("--out", type=click.Path(file_okay=False), default=None,
              help="New zarr recording to write (REC.zarr: one chunk per sequence, xarray / dask readable), with "
                   "preview.png inside.")
@click.option("--frames", "raw_frames", is_flag=True, help="Also record the raw frames (for specgpu batch).")
@click.option("--outputs", default="coefficients,XYZ,dE", show_default=True,
              help="Comma-separated: coefficients, cube, XYZ, Lab, dE, sigma (each output's standard deviation and "
                   "their RMS), sigma_rms (that RMS alone), dE_sigma (first-order dE2000 standard deviation); the "
                   "sigmas use the noise model specgpu plan records (a plan of a custom rig needs plan --rig).")
@click.option("--delta-e-ref", "ref", default=None,
              help="dE reference: 'L,a,b' or a scene whose Lab per pixel is it (default: the streamed scene).")
@click.option("--method", default="CIE 2000", show_default=True, help="CIE 1976, CIE 1994 or CIE 2000.")
@_ILLUMINANT
@_OBSERVER
@click.option("--pacing", type=click.Choice(["paced", "free"]), default="paced", show_default=True,
              help="Twin pacing: at the camera's frame rate, or as fast as it renders.")
@click.option("--policy", type=click.Choice(["drop_newest", "drop_oldest", "block"]), default=None,
              help="Frame ring policy when the pipeline falls behind (default: drop_newest when paced, as a "
                   "camera never waits; block when free-running, where the simulated camera can).")
@click.option("--exr-every", type=click.IntRange(min=0), default=0, show_default=True,
              help="Also write every N-th result as EXR maps into --out (0: none).")
@click.option("--half", is_flag=True, help="Keep the cube in half precision.")
@click.option("--seed", type=click.IntRange(min=0, max=2**63 - 1), default=None,
              help="Seed of the frames' temporal noise.")
@click.option("--device", "device", default=None, help="OpenCL device selector.")
@click.option("--white-roi", default=None, metavar="X,Y,W,H",
              help="A reference white in the field: rescale each sequence's decoder for the light's drift (as "
                   "recover --white-roi; the gains are recorded).")
@click.option("--white-reflectance", default=None, metavar="VALUE|CSV",
              help="Reflectance of the --white-roi white: a number or a CSV (wavelength nm, value). [0.99]")
@_RESIZE
@click.option("--no-disk-check", is_flag=True,
              help="Record even when a write probe says the disk cannot keep up with --out (frames will be "
                   "dropped); also skips the probe that chooses each array's compression.")
def stream_command(rig_path, plan_path, calib, scene, seconds, out, raw_frames, outputs, ref, method, illuminant,
                   observer, pacing, policy, exr_every, half, seed, device, white_roi, white_reflectance, resize,
                   no_disk_check):
    """Stream a plan's sequences from the rig through the device to maps, with a live status line; Ctrl-C
    stops cleanly (everything captured is processed or reported)."""
    from specgpu.capture.twin import TwinDriver
    from specgpu.pipeline.recovery import check_scene_covers
    from specgpu.rig.twin import TwinRig
    from specgpu.pipeline import STREAM_OUTPUTS
    from specgpu.core.validate import validate_method

    # before any loading: a typo is an error naming the valid outputs
    wanted = tuple(validate_method(o.strip(), {k: k for k in STREAM_OUTPUTS}, "stream output")
                   for o in outputs.split(",") if o.strip())
    if white_reflectance is not None and white_roi is None:
        raise click.UsageError("--white-reflectance needs --white-roi")
    from specgpu.rig.config import load_rig

    if out:
        from specgpu.io.recording import refuse_existing

        _lock(out, folder=True)  # one recorder per folder: a second stream into it refuses at once
        refuse_existing(out)  # before any work: a recording is never mixed with another run
    description = load_rig(rig_path)
    hardware = _hardware(description)  # a typo in [hardware] first, before any device or file work
    bundle, plan, truth = _experiment(description, plan_path, calib, scene, resize)
    illuminant = plan.resolve_illuminant(illuminant, name=str(plan_path))
    observer = plan.resolve_observer(observer, name=str(plan_path))
    cam = description.camera
    check_scene_covers(truth, plan, description.light.line_fwhm_nm)
    reference = None
    if "dE" in wanted:
        # default: the streamed scene itself, as fitted to the frame above
        reference = _parse_reference(ref or truth, cam.roi_height, cam.roi_width, illuminant, resize,
                                     observer=observer)
    if hardware is None:
        rig = TwinRig(plan.rig_description(description), scene=truth)
        if seed is not None:
            rig.seed = seed
        driver = TwinDriver(rig, patterns=plan.patterns, pacing=pacing)
    else:  # real devices: the plan uploaded to the light, frames from the camera (a camera never waits)
        from specgpu.hardware.rig import open_hardware

        driver = open_hardware(description, hardware=hardware, patterns=plan.patterns, calibration=bundle,
                               exposure_s=plan.exposure_s)  # the plan's, as the twin uses it
        pacing = "paced"
    try:
        _stream_run(driver, description, plan, bundle, truth, wanted, reference, out, raw_frames, plan_path, calib,
                    seconds, method, (illuminant, observer), pacing, policy, exr_every, half, seed, device,
                    white=(white_roi, white_reflectance), disk_check=not no_disk_check)
    finally:
        if hardware is not None:
            driver.close()  # the light's USB link and the camera


#: Seconds of frames the frame ring of a recording stream holds.
_RECORD_RING_S = 2.0


def _stream_run(driver, description, plan, bundle, truth, wanted, reference, out, raw_frames, plan_path, calib,
                seconds, method, colours, pacing, policy, exr_every, half, seed, device, white=(None, None),
                disk_check=True):
    """The stream of ``specgpu stream`` once its driver is open: the recording set up, run, summarised;
    ``colours``: the (illuminant, observer) of its XYZ, Lab and dE."""
    import numpy as np

    from specgpu.pipeline import ExrSequenceWriter, PreviewSink, Stream

    cam = description.camera
    illuminant, observer = colours
    policy = policy or ("drop_newest" if pacing == "paced" else "block")
    white_roi, white_reflectance = white
    # a recording keeps every frame rather than the least latency: a frame ring of 2 s of frames rides out the
    # stalls of a loaded machine or disk (the default ring, 4 sequences, favours latency)
    n_slots = None
    if out:
        import math

        rate = plan.rig_description(description).camera.frame_rate_hz
        n_slots = max(4 * plan.K, 16, math.ceil(_RECORD_RING_S * rate))
    stream = Stream(driver, plan, bundle, outputs=wanted, reference=reference, method=method,
                    illuminant=illuminant, observer=observer, cube_dtype=np.float16 if half else np.float32,
                    policy=policy,
                    device=device, white_roi=white_roi, white_reflectance=white_reflectance, n_slots=n_slots)
    sinks, writer = stream.sinks, None
    if out:
        from pathlib import Path

        from specgpu.io.recording import (ZarrRecorder, check_free_space, check_write_rate, expected_sequences,
                                sequence_bytes)

        frame_rate = plan.rig_description(description).camera.frame_rate_hz
        n_expected = expected_sequences(seconds, frame_rate, plan.K)
        per_sequence = sequence_bytes(stream.decoder.shapes(), frames_shape=(plan.K, cam.roi_height,
                                                                             cam.roi_width) if raw_frames else None)
        check_free_space(out, n_expected * per_sequence,
                         what=f"the recording ({n_expected} sequences x {per_sequence / 1e6:.1f} MB)")
        disk_rate = None
        if disk_check:
            # before any frame: a disk slower than the recording makes a camera that never waits drop frames
            # (a blocking ring only slows the run down, so there the probe only chooses the compression)
            # (large chunks bypass the system's write buffer: what can wait is the stream's frame ring)
            per_s = frame_rate / plan.K
            disk_rate = check_write_rate(
                out, per_sequence * per_s, seconds if policy != "block" else 0.0,
                what=f"the recording ({per_sequence / 1e6:.1f} MB a sequence x {per_s:.1f} sequences/s)",
                buffer_bytes=_RECORD_RING_S * per_sequence * per_s)
        meta = {"scene": truth.name, "illuminant": illuminant, "observer": observer, "method": method, "seed": seed,
                **({"scene_resampled": truth.resampled} if truth.resampled else {}),
                **({"white_roi": white_roi, "white_reflectance": white_reflectance or 0.99} if white_roi else {})}
        writer = ZarrRecorder(out, plan, frames=raw_frames, basis=stream.decoder.basis, metadata=meta,
                              disk_rate=disk_rate)
        import shutil

        shutil.copyfile(plan_path, Path(out) / "plan.npz")  # what batch re-processes the frames with
        shutil.copyfile(calib, Path(out) / "calibration.npz")
        sinks.append(writer)
        if exr_every:
            sinks.append(ExrSequenceWriter(Path(out) / "exr", wavelengths=plan.output_wavelengths, every=exr_every,
                                           dE_kind={"CIE 1976": "dE76", "CIE 1994": "dE94"}.get(method, "dE2000"),
                                           metadata=meta))
        if "XYZ" in wanted:
            sinks.append(PreviewSink(Path(out) / "preview.png", illuminant=illuminant, observer=observer))
    tty = sys.stderr.isatty()

    def status(s):
        line = (f"frames in {s['frames_in']}, sequences out {s['sequences_out']}, drops {s['assembler_dropped']} "
                f"(ring {s['ring_dropped']}), discarded {s['discarded']}, latency {s['latency_ms']:.1f} ms")
        click.echo(("\r" + line + "   ") if tty else line, err=True, nl=not tty)

    try:
        with _one_interrupt():
            report = stream.run(seconds, on_status=status)
    except BaseException as error:  # the recording says it failed (never "complete"), with the reason
        if writer is not None and not isinstance(error, KeyboardInterrupt):
            writer.mark_failed(f"{type(error).__name__}: {error}")
        raise
    if tty:
        click.echo("", err=True)
    a = report.assembly
    click.echo(f"{report.frames_in} frames in ({report.frames_per_s:.0f}/s), {report.sequences_out} sequences out "
               f"({report.sequences_per_s:.1f}/s); dropped {a.dropped} (ring {report.ring.dropped}), duplicated "
               f"{a.duplicates}, missed triggers {a.missed_triggers}, discarded {a.sequences_discarded}; latency "
               f"median {report.latency_ms(50):.1f} ms, p99 {report.latency_ms(99):.1f} ms"
               + (" (interrupted)" if report.interrupted else "")
               + (f"; wrote {out} ({writer.committed} sequences)" if out and not report.sink_errors else ""))
    if report.sink_errors:
        saved = (f"; {writer.committed} sequences saved in {out}, {report.sequences_out - writer.committed} lost"
                 if writer is not None else "")
        raise click.ClickException(f"a sink failed: {report.sink_errors[0]}{saved}")


@main.command("batch")
@click.argument("source", type=click.Path(exists=True, file_okay=False))
@_PLAN
@click.option("--calib", default=None, type=click.Path(exists=True, dir_okay=False),
              help="Calibration the plan was made from (default: SOURCE/calibration.npz).")
@click.option("--out", required=True, type=click.Path(file_okay=False),
              help="Output zarr (OUT.zarr); an existing one from the same batch is resumed.")
@click.option("--outputs", default="cube", show_default=True, help="Comma-separated: cube, XYZ, Lab, dE.")
@click.option("--delta-e-ref", "ref", default=None, help="dE reference: 'L,a,b' or a scene whose Lab per pixel is it.")
@click.option("--method", default="CIE 2000", show_default=True, help="CIE 1976, CIE 1994 or CIE 2000.")
@_ILLUMINANT
@_OBSERVER
@click.option("--scheduler", default=None, help="Address of a dask.distributed scheduler (default: a LocalCluster).")
@click.option("--workers", type=click.IntRange(min=1), default=1, show_default=True,
              help="LocalCluster worker processes (one thread and one OpenCL context each).")
@click.option("--device", "device", default=None, help="OpenCL device selector (on every worker).")
@_RESIZE
def batch_command(source, plan_path, calib, out, outputs, ref, method, illuminant, observer, scheduler, workers,
                  device, resize):
    """Re-process the raw frames of a recording (specgpu stream --frames) or a sequence folder with a plan, on
    Dask: one task per sequence, resumable, equal to specgpu recover of each sequence."""
    from pathlib import Path

    from specgpu.pipeline.batch import BATCH_OUTPUTS, open_source, run_batch
    from specgpu.calibration.bundle import load_calibration
    from specgpu.engine.colorimetry import DELTA_E_METHODS
    from specgpu.planning.plans import load_plan
    from specgpu.core.validate import validate_method

    wanted = tuple(validate_method(o.strip(), {k: k for k in BATCH_OUTPUTS}, "batch output")
                   for o in outputs.split(",") if o.strip())
    method = validate_method(method, DELTA_E_METHODS)
    if ("dE" in wanted) != (ref is not None):
        raise click.UsageError("the dE output and --delta-e-ref go together")
    plan = load_plan(plan_path)
    illuminant = plan.resolve_illuminant(illuminant, name=str(plan_path))
    observer = plan.resolve_observer(observer, name=str(plan_path))
    calib = Path(calib) if calib else Path(source) / "calibration.npz"
    if not calib.is_file():
        raise click.UsageError(f"{calib} not found; give --calib")
    bundle = load_calibration(calib)
    plan.check_calibration(bundle, name=str(plan_path), calibration_name=str(calib))  # names both files
    reference = None
    if ref is not None:
        src = open_source(source)
        reference = _parse_reference(ref, src.height, src.width, illuminant, resize, observer=observer)
    report = run_batch(source, plan, bundle, out, outputs=wanted, illuminant=illuminant, observer=observer,
                       method=method, reference=reference, scheduler=scheduler, workers=workers, device=device)
    click.echo(f"{plan.method}: {report.computed} sequences computed on {report.workers} worker(s) in "
               f"{report.seconds:.1f} s ({report.sequences_per_s:.1f} sequences/s), {report.skipped} already done; "
               f"OpenCL contexts built {report.contexts_built}; wrote {out}")


@main.command()
@click.argument("cube", type=click.Path(exists=True, dir_okay=False))
@click.option("--truth", required=True,
              help="The true scene: colorchecker, white, natural[:image] or a .exr / .npz / .hdr (ENVI) cube.")
@click.option("--illuminant", default=None,
              help="Illuminant of the colour differences [default: the one the file records (a tristimulus plan's "
                   "own), else D65]; another than an XYZ map records is refused.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), default=None, help="Write the report here.")
@click.option("--device", "device", default=None, help="OpenCL device selector.")
@_RESIZE
def evaluate(cube, truth, illuminant, json_path, device, resize):
    """Accuracy of a recovered cube (.exr, .npz or ENVI .hdr; or an XYZ map) against the true scene: per pixel,
    and per patch for a chart."""
    import json

    import numpy as np

    from specgpu import io
    from specgpu.pipeline.evaluate import evaluate_pixels, evaluate_reflectance, evaluate_XYZ, evaluation_illuminant
    from specgpu.rig.scene import load_scene
    from specgpu.core.spectra import DEFAULT_CMFS

    if json_path:
        from pathlib import Path

        _no_clash([("--json", json_path)], [("CUBE", cube), ("--truth", truth if Path(truth).exists() else None)])
        _lock(json_path)
    try:
        data, wavelengths, meta = io.read_cube(cube)
    except ValueError as cube_error:
        try:  # a tristimulus recovery: an XYZ map
            data, _, meta = io.read_map(cube, "XYZ")
            wavelengths = None
        except ValueError:
            raise cube_error from None
    illuminant = evaluation_illuminant(meta.get("illuminant"), illuminant, colorimetric=wavelengths is None,
                                       name=str(cube))
    # XYZ is also relative to the observer it was made for (a tristimulus plan's, recorded by recover)
    cmfs = meta.get("observer") if wavelengths is None and isinstance(meta.get("observer"), str) else DEFAULT_CMFS
    height, width = data.shape[:2]
    scene = _resampled(f"--truth {truth}", load_scene(truth, height, width, resize=resize))
    with _Busy("evaluating"):
        pixels = evaluate_pixels(data, scene, wavelengths=wavelengths, illuminant=illuminant, cmfs=cmfs,
                                 device=device)
    stats = pixels.statistics()
    report = {"cube": str(cube), "truth": scene.name, "illuminant": illuminant,
              **({"observer": cmfs} if cmfs != DEFAULT_CMFS else {}),
              **({"truth_resampled": scene.resampled} if scene.resampled else {}),
              "projections": meta.get("projections"), "plan_method": meta.get("plan_method"), "pixels": stats}
    headline = {k: stats[k] for k in stats}
    if scene.masks:
        patch = (evaluate_reflectance(data, wavelengths, scene, illuminant=illuminant) if wavelengths is not None
                 else evaluate_XYZ(data, scene, illuminant=illuminant, cmfs=cmfs))
        rows = []
        for i, name in enumerate(patch.names):
            row = {"patch": name, "dE76": float(patch.delta_E_ab[i]), "dE2000": float(patch.delta_E_2000[i])}
            if patch.rmse is not None:
                row["rmse"] = float(patch.rmse[i])
            rows.append(row)
        report["patches"] = rows
        # the headline figures of a chart are per patch, like the paper's tables
        headline = {k: {"mean": float(np.mean(v)), "max": float(np.max(v))} for k, v in
                    (("rmse", patch.rmse), ("delta_E_ab", patch.delta_E_ab), ("delta_E_2000", patch.delta_E_2000))
                    if v is not None}
        click.echo(f"{'patch':<22}{'RMSE':>8}{'dE*ab':>8}{'dE2000':>8}")
        for row in rows:
            rmse = f"{row['rmse']:8.4f}" if "rmse" in row else f"{'-':>8}"
            click.echo(f"{row['patch']:<22}{rmse}{row['dE76']:8.2f}{row['dE2000']:8.2f}")
    names = {"rmse": "rmse", "delta_E_ab": "dE76", "delta_E_2000": "dE2000"}
    for key, short in names.items():
        if key in headline:
            report[f"{short}_mean"] = headline[key]["mean"]
            report[f"{short}_max"] = headline[key]["max"]
    basis = "per patch" if scene.masks else "per pixel"
    click.echo(f"{basis} under {illuminant}: " + ", ".join(f"{names[k]} mean {v['mean']:.4g} max {v['max']:.4g}"
                                        for k, v in headline.items())
               + (f"; {report['projections']} projections" if report["projections"] else ""))
    if json_path:
        with io.atomic_path(Path(json_path)) as tmp:
            tmp.write_text(json.dumps(report, indent=1))


@main.command()
@click.option("--out", default="specgpu-report", show_default=True, type=click.Path(file_okay=False),
              help="Report folder.")
@_RIG
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--device", "device", default=None, help="OpenCL device selector.")
@click.option("--draws", type=click.IntRange(1, 50), default=2, show_default=True,
              help="Noise draws per method and profile (tables give mean +- std).")
def demo(out, rig_path, seed, device, draws):
    """The main job on the built-in twin: calibrate, plan, capture the chart, recover, evaluate; prints the
    paper's Tables 1-3 beside ours and writes a report folder with index.html."""
    from specgpu.apps.demo import format_tables, run_demo

    _lock(out, folder=True)
    result = run_demo(out, rig=rig_path, seed=seed, echo=click.echo, device=device, draws=draws)
    click.echo(format_tables(result))
    click.echo(f"\ndemo finished in {result.seconds:.1f} s; report: {result.out / 'index.html'}")


if __name__ == "__main__":  # pragma: no cover
    main()
