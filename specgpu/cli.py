"""The ``specgpu`` command.

Every command has --help, exits 0 on success and, on failure, prints one line saying why and exits non-zero.
"""

from __future__ import annotations

import sys

import click

from . import __version__


class _Group(click.Group):
    """Turns any error a command raises into one line on stderr and exit status 1 (2 for usage errors)."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (click.ClickException, click.exceptions.Exit, click.exceptions.Abort, SystemExit):
            raise
        except KeyboardInterrupt:
            click.echo("specgpu: interrupted", err=True)
            sys.exit(130)
        except Exception as error:  # noqa: BLE001 (the CLI promises one line, not a traceback)
            message = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
            raise click.ClickException(message) from error


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="specgpu")
def main():
    """specgpu: active-illumination spectral imaging on OpenCL (Tominaga and Horiuchi, JOSA A 2012)."""


@main.command()
@click.option("--device", "device", default=None, help="Device selector: 'P:D' indices or a name substring.")
@click.option("--devices", "usb", is_flag=True, help="Also list the USB devices found (light sources specgpu drives).")
def info(device, usb):
    """OpenCL platforms and devices, the one chosen, and versions; with --devices, the USB devices."""
    from .runtime import describe

    click.echo(describe(device))
    if usb:
        from .hardware.usb import list_usb_devices

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
    from .selftest import run_selftest

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
@click.option("--stream-cases", default="fused,cube,paced,overload,equality", show_default=True,
              help="With --stream: comma-separated cases to run.")
def bench(device, json_path, sizes, repeats, stream, stream_size, stream_seconds, paced_seconds, stream_cases):
    """Throughput of each kernel against NumPy / colour-science baselines measured in the same run."""
    from .bench import parse_sizes, run_bench

    if stream:
        from .bench import run_stream_bench

        try:
            (width, height), = parse_sizes(stream_size)
        except ValueError as error:
            raise click.BadParameter(str(error), param_hint="--stream-size") from error
        cases = tuple(c.strip() for c in stream_cases.split(",") if c.strip())
        run_stream_bench(seconds=stream_seconds, paced_seconds=paced_seconds, overload_seconds=stream_seconds,
                         width=width, height=height, device=device, json_path=json_path, echo=click.echo,
                         cases=cases)
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
                                                   "cube (default: the rig's [scene] source).")


def _hardware(description):
    """The rig's [hardware] table checked (None for the twin)."""
    if not description.hardware:
        return None
    from .hardware.rig import HardwareConfig

    return HardwareConfig.from_dict(description.hardware, source=description.source,
                                    base_dir=description.base_dir or None)


def _experiment(description, plan_path, calib, scene):
    """The rig's calibration, a plan made from that calibration (stale: an error) and the scene at the camera's
    resolution: what capture and stream both start from."""
    from .calibration import load_calibration
    from .plans import load_plan
    from .rig.scene import load_scene

    bundle = load_calibration(calib, rig=description)
    plan = load_plan(plan_path)
    plan.check_calibration(bundle, name=str(plan_path))
    cam = description.camera
    return bundle, plan, load_scene(scene or description.scene, cam.roi_height, cam.roi_width)


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
@click.option("--seed", type=int, default=0, show_default=True,
              help="Seed of the twin's noise; on hardware, of the loops' perturbed start only.")
def calibrate(rig_path, out, seed):
    """Run both feedback loops on the rig and write the calibration bundle."""
    from .calibration import calibrate as run, save_calibration
    from .rig.config import load_rig

    description = load_rig(rig_path)
    hardware = _hardware(description)
    with _Busy("calibrating"):
        if hardware is None:
            bundle = run(description, seed=seed)
        else:  # real devices: the camera looks at the reference white, the spectrometer at the light's output
            from .hardware.rig import open_calibration_rig

            with open_calibration_rig(description, hardware=hardware) as rig:
                bundle = run(description, seed=seed, rig=rig)
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
@click.option("--step-nm", type=float, default=10.0, show_default=True, help="Band spacing (narrowband, reciprocal).")
@click.option("--bandwidth-nm", type=float, default=None, help="Band width (narrowband, reciprocal; default the step).")
@click.option("--m", "m", type=int, default=5, show_default=True, help="Basis functions (biased, symmetric).")
@click.option("--basis", "basis_path", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Basis table (.npz); default: PCA of colour-science's reflectances without --exclude-chart.")
@click.option("--exclude-chart", default="ColorChecker N Ohta", show_default=True,
              help="Chart left out of the default basis training (the one you evaluate on).")
@click.option("--output-step-nm", type=float, default=10.0, show_default=True,
              help="Output wavelength spacing of basis methods (400-700 nm).")
@click.option("--illuminant", default="D65", show_default=True, help="Tristimulus / camera simulator illuminant.")
@click.option("--observer", default="CIE 1931 2 Degree Standard Observer", show_default=True)
@click.option("--camera", default="Nikon 5100 (NPL)", show_default=True, help="Camera simulator: sensitivities.")
@click.option("--spectrum", default="D65", show_default=True,
              help="Steady-state: target illuminant name (colour-science) for spectral rendering.")
@click.option("--ambient", is_flag=True,
              help="Add an ambient frame (every mirror off) to each sequence; recover subtracts it (1 frame more).")
def plan_command(method, calib, out, step_nm, bandwidth_nm, m, basis_path, exclude_chart, output_step_nm,
                 illuminant, observer, camera, spectrum, ambient):
    """Design a measurement plan: the illuminant sequence and its decoder.

    METHOD is one of: narrowband, reciprocal, biased, symmetric, tristimulus, camera, steady.
    """
    import numpy as np

    from .calibration import load_calibration
    from .plans import PLAN_METHODS, make_plan, save_plan
    from .validate import validate_method

    validate_method(method, {k: k for k in PLAN_METHODS}, "METHOD")
    method = method.lower()
    bundle = load_calibration(calib)
    if method in ("narrowband", "reciprocal"):
        kwargs = {"step_nm": step_nm, "bandwidth_nm": bandwidth_nm}
        args = ()
    elif method in ("biased", "symmetric"):
        if basis_path:
            from .basis import load_basis

            basis = load_basis(basis_path)
        else:
            from .pipeline import default_basis

            with _Busy("building the basis"):
                basis = default_basis(exclude_chart)
        args = (basis,)
        kwargs = {"m": m, "output_wavelengths": np.arange(400.0, 700.0 + 1e-9, output_step_nm)}
    elif method == "tristimulus":
        args, kwargs = (), {"illuminant": illuminant, "cmfs": observer}
    elif method == "camera":
        args, kwargs = (), {"camera": camera, "illuminant": illuminant}
    else:  # steady
        from .render import target_spectrum

        sd = target_spectrum(spectrum)
        args, kwargs = (sd.values, sd.wavelengths), {}
    plan = make_plan(method, bundle, *args, **kwargs)
    if ambient:
        from .correction import with_ambient_frame

        plan = with_ambient_frame(plan)
    digest = save_plan(out, plan)
    click.echo(f"{plan.method}: {plan.K} frames at {plan.exposure_s * 1e3:.2f} ms, {plan.A.shape[0]} outputs "
               f"({plan.output}); wrote {out} (plan {digest[:12]}, calibration {plan.calibration[:12]})")


@main.command()
@_RIG
@_PLAN
@click.option("--calib", required=True, type=click.Path(exists=True, dir_okay=False),
              help="The calibration the plan was made from (stored with the frames for recovery).")
@_SCENE
@click.option("--out", required=True, type=click.Path(file_okay=False), help="Sequence folder to write.")
@click.option("--sequences", type=click.IntRange(min=1), default=1, show_default=True)
@click.option("--seed", type=int, default=None, help="Seed of the frames' temporal noise.")
def capture(rig_path, plan_path, calib, scene, out, sequences, seed):
    """Capture sequences of a plan on the rig (the twin by default) into a sequence folder."""
    from tqdm import tqdm

    from .pipeline import capture_plan, write_capture
    from .rig.config import load_rig

    description = load_rig(rig_path)
    hardware = _hardware(description)  # a typo in [hardware] first, before any device or file work
    bundle, plan, truth = _experiment(description, plan_path, calib, scene)
    cam = description.camera
    kept = []
    with tqdm(total=sequences, desc="capturing", unit="seq", leave=False, file=sys.stderr) as bar:
        def keep(sequence):
            kept.append(sequence)
            bar.update()

        if hardware is None:
            result = capture_plan(description, plan, truth, sequences=sequences, noise_seed=seed, on_sequence=keep,
                                  calibration=bundle)
        else:  # real devices: the same ring buffer and assembler, the plan uploaded to the light
            from .capture.session import capture_sequences
            from .hardware.rig import open_hardware

            driver = open_hardware(description, hardware=hardware, patterns=plan.patterns, calibration=bundle,
                                   n_frames=plan.K * sequences)
            try:
                result = capture_sequences(driver, plan.K, on_sequence=keep)
            finally:
                driver.close()
    write_capture(out, kept, result.assembly, plan_path, calib,
                  metadata={"scene": truth.name, "rig": rig_path or "<paper defaults>"})
    a = result.assembly
    click.echo(f"{len(kept)} sequences of {plan.K} frames ({truth.name}, {cam.roi_width} x {cam.roi_height}); "
               f"dropped {a.dropped}, duplicated {a.duplicates}, missed triggers {a.missed_triggers}, "
               f"discarded {a.sequences_discarded}; wrote {out}")


def _parse_reference(text, height, width, illuminant):
    """--delta-e-ref: an 'L,a,b' colour, or a scene (built-in name or cube file) whose Lab is the reference."""
    import numpy as np

    parts = text.split(",")
    if len(parts) == 3:
        try:
            return np.array([float(p) for p in parts], np.float32)
        except ValueError:
            pass
    from .colorimetry import XYZ_to_Lab
    from .evaluate import scene_XYZ
    from .rig.scene import load_scene

    return XYZ_to_Lab(scene_XYZ(load_scene(text, height, width), illuminant), illuminant)


@main.command()
@click.argument("seq", type=click.Path(exists=True, file_okay=False))
@click.option("--out", required=True, type=click.Path(dir_okay=False),
              help="Recovered cube (.exr / .npz); an XYZ map for a tristimulus plan.")
@click.option("--xyz", "xyz_path", type=click.Path(dir_okay=False), default=None, help="Also write XYZ (EXR).")
@click.option("--lab", "lab_path", type=click.Path(dir_okay=False), default=None, help="Also write CIELAB (EXR).")
@click.option("--delta-e-ref", "ref", default=None,
              help="Reference: 'L,a,b', or a scene whose true colour per pixel (over all its bands) is it.")
@click.option("--delta-e", "de_path", type=click.Path(dir_okay=False), default=None,
              help="Colour-difference map to write (EXR; .png for a heat map).")
@click.option("--method", default="CIE 2000", show_default=True, help="CIE 1976, CIE 1994 or CIE 2000.")
@click.option("--illuminant", default="D65", show_default=True, help="Illuminant of XYZ, Lab and dE.")
@click.option("--sequence", type=int, default=None, help="Recover one sequence (default: the mean of all).")
@click.option("--half", is_flag=True, help="Write the cube in half precision.")
@click.option("--device", "device", default=None, help="OpenCL device selector.")
@click.option("--white-roi", default=None, metavar="X,Y,W,H",
              help="A reference white in the field: rescale each sequence's decoder for the light's drift.")
@click.option("--white-reflectance", default=None, metavar="VALUE|CSV",
              help="Reflectance of the --white-roi white: a number or a CSV (wavelength nm, value). [0.99]")
def recover(seq, out, xyz_path, lab_path, ref, de_path, method, illuminant, sequence, half, device, white_roi,
            white_reflectance):
    """Recover a sequence folder: the cube and, when asked, XYZ, Lab and dE maps (written only if all succeed)."""
    from pathlib import Path

    import numpy as np

    from . import io
    from .colorimetry import DELTA_E_METHODS, delta_E
    from .pipeline import read_capture, recover as run, to_Lab, to_XYZ
    from .validate import validate_method

    if (ref is None) != (de_path is None):
        raise click.UsageError("--delta-e-ref and --delta-e go together")
    method = validate_method(method, DELTA_E_METHODS)
    folder = read_capture(seq)
    plan = folder.plan
    with _Busy("recovering"):
        if white_reflectance is not None and white_roi is None:
            raise click.UsageError("--white-reflectance needs --white-roi")
        try:
            y = run(folder, sequence=sequence, device=device, white_roi=white_roi, white_reflectance=white_reflectance)
        except ValueError as error:
            raise click.ClickException(str(error)) from None
        height, width = y.shape[:2]
        meta = {"plan_method": plan.method, "projections": plan.K, "plan_hash": plan.hash,
                "calibration": plan.calibration, "sequence_folder": str(seq),
                "sequences_averaged": 1 if sequence is not None else folder.sequences, "illuminant": illuminant,
                **({"white_roi": white_roi, "white_reflectance": white_reflectance or 0.99} if white_roi else {}),
                **({"reflectance_scale_uncertainty": folder.calibration.reports["white_reflectance_uncertainty"]}
                   if "white_reflectance_uncertainty" in folder.calibration.reports else {})}
        writes = []
        if plan.output == "reflectance":
            writes.append(lambda: io.write_cube(out, y, plan.output_wavelengths, half=half, metadata=meta))
        else:
            kind = "XYZ" if plan.output == "XYZ" else tuple(plan.output_labels)
            writes.append(lambda: io.write_map(out, y, kind, half=half, metadata=meta))
        XYZ = Lab = None
        if xyz_path or lab_path or de_path:
            XYZ = to_XYZ(y, plan, illuminant, device=device)
            Lab = to_Lab(XYZ, illuminant, device=device)
        if xyz_path:
            writes.append(lambda: io.write_map(xyz_path, XYZ, "XYZ", metadata=meta))
        if lab_path:
            writes.append(lambda: io.write_map(lab_path, Lab, "Lab", metadata=meta))
        if de_path:
            dE = delta_E(_parse_reference(ref, height, width, illuminant), Lab, method, device=device)
            if Path(de_path).suffix.lower() == ".png":
                writes.append(lambda: io.write_delta_E_png(de_path, dE, metadata=meta))
            else:
                kind = {"CIE 1976": "dE76", "CIE 1994": "dE94", "CIE 2000": "dE2000"}[method]
                writes.append(lambda: io.write_map(de_path, dE, kind, metadata=meta))
    written = []
    try:
        for write in writes:
            written.append(write())
    except Exception:
        for path in written:  # nothing partial left looking complete
            Path(path).unlink(missing_ok=True)
        raise
    saturated = int(np.isnan(y[..., 0]).sum())
    note = f"; {saturated} saturated pixels left NaN" if saturated else ""
    click.echo(f"{plan.method}: {plan.K} projections, {folder.sequences} sequences in {seq}; wrote "
               + ", ".join(str(p) for p in written) + note)


@main.command("stream")
@_RIG
@_PLAN
@click.option("--calib", required=True, type=click.Path(exists=True, dir_okay=False),
              help="The calibration the plan was made from.")
@_SCENE
@click.option("--seconds", type=click.FloatRange(min=0, min_open=True), required=True, help="Capture time.")
@click.option("--out", type=click.Path(file_okay=False), default=None,
              help="Folder for the recording (chunked .npy + index.json) and preview.png.")
@click.option("--outputs", default="coefficients,XYZ,dE", show_default=True,
              help="Comma-separated: coefficients, cube, XYZ, Lab, dE.")
@click.option("--delta-e-ref", "ref", default=None,
              help="dE reference: 'L,a,b' or a scene whose Lab per pixel is it (default: the streamed scene).")
@click.option("--method", default="CIE 2000", show_default=True, help="CIE 1976, CIE 1994 or CIE 2000.")
@click.option("--illuminant", default="D65", show_default=True, help="Illuminant of XYZ, Lab and dE.")
@click.option("--pacing", type=click.Choice(["paced", "free"]), default="paced", show_default=True,
              help="Twin pacing: at the camera's frame rate, or as fast as it renders.")
@click.option("--policy", type=click.Choice(["drop_newest", "drop_oldest", "block"]), default=None,
              help="Frame ring policy when the pipeline falls behind (default: drop_newest when paced, as a "
                   "camera never waits; block when free-running, where the simulated camera can).")
@click.option("--exr-every", type=click.IntRange(min=0), default=0, show_default=True,
              help="Also write every N-th result as EXR maps into --out (0: none).")
@click.option("--half", is_flag=True, help="Keep the cube in half precision.")
@click.option("--seed", type=int, default=None, help="Seed of the frames' temporal noise.")
@click.option("--device", "device", default=None, help="OpenCL device selector.")
def stream_command(rig_path, plan_path, calib, scene, seconds, out, outputs, ref, method, illuminant, pacing,
                   policy, exr_every, half, seed, device):
    """Stream a plan's sequences from the rig through the device to maps, with a live status line; Ctrl-C
    stops cleanly (everything captured is processed or reported)."""
    import numpy as np

    from .capture.twin import TwinDriver
    from .pipeline import check_scene_covers
    from .rig.twin import TwinRig
    from .stream import STREAM_OUTPUTS, ExrSequenceWriter, NpyChunkWriter, PreviewSink, Stream
    from .validate import validate_method


    # before any loading: a typo is an error naming the valid outputs
    wanted = tuple(validate_method(o.strip(), {k: k for k in STREAM_OUTPUTS}, "stream output")
                   for o in outputs.split(",") if o.strip())
    from .rig.config import load_rig

    description = load_rig(rig_path)
    bundle, plan, truth = _experiment(description, plan_path, calib, scene)
    cam = description.camera
    check_scene_covers(truth, plan, description.light.line_fwhm_nm)
    reference = None
    if "dE" in wanted:
        reference = _parse_reference(ref, cam.roi_height, cam.roi_width, illuminant) if ref else \
            _parse_reference(str(scene or description.scene), cam.roi_height, cam.roi_width, illuminant)
    rig = TwinRig(plan.rig_description(description), scene=truth)
    if seed is not None:
        rig.seed = seed
    driver = TwinDriver(rig, patterns=plan.patterns, pacing=pacing)
    sinks, writer = [], None
    if out:
        from pathlib import Path

        meta = {"plan_hash": plan.hash, "plan_method": plan.method, "calibration": plan.calibration,
                "scene": truth.name, "illuminant": illuminant, "outputs": list(wanted)}
        writer = NpyChunkWriter(out, metadata=meta)
        sinks.append(writer)
        if exr_every:
            sinks.append(ExrSequenceWriter(Path(out) / "exr", wavelengths=plan.output_wavelengths, every=exr_every,
                                           dE_kind={"CIE 1976": "dE76", "CIE 1994": "dE94"}.get(method, "dE2000"),
                                           metadata=meta))
        if "XYZ" in wanted:
            sinks.append(PreviewSink(Path(out) / "preview.png"))
    policy = policy or ("drop_newest" if pacing == "paced" else "block")
    stream = Stream(driver, plan, bundle, outputs=wanted, sinks=sinks, reference=reference, method=method,
                    illuminant=illuminant, cube_dtype=np.float16 if half else np.float32, policy=policy,
                    device=device)
    if writer is not None and stream.decoder.basis is not None:
        writer.metadata["coefficient_basis"] = stream.decoder.basis.tolist()
    tty = sys.stderr.isatty()

    def status(s):
        line = (f"frames in {s['frames_in']}, sequences out {s['sequences_out']}, drops {s['assembler_dropped']} "
                f"(ring {s['ring_dropped']}), discarded {s['discarded']}, latency {s['latency_ms']:.1f} ms")
        click.echo(("\r" + line + "   ") if tty else line, err=True, nl=not tty)

    report = stream.run(seconds, on_status=status)
    if tty:
        click.echo("", err=True)
    a = report.assembly
    click.echo(f"{report.frames_in} frames in ({report.frames_per_s:.0f}/s), {report.sequences_out} sequences out "
               f"({report.sequences_per_s:.1f}/s); dropped {a.dropped} (ring {report.ring.dropped}), duplicated "
               f"{a.duplicates}, missed triggers {a.missed_triggers}, discarded {a.sequences_discarded}; latency "
               f"median {report.latency_ms(50):.1f} ms, p99 {report.latency_ms(99):.1f} ms"
               + (" (interrupted)" if report.interrupted else "") + (f"; wrote {out}" if out else ""))
    if report.sink_errors:
        raise click.ClickException(f"a sink failed: {report.sink_errors[0]}")


@main.command()
@click.argument("cube", type=click.Path(exists=True, dir_okay=False))
@click.option("--truth", required=True, help="The true scene: colorchecker, white, natural[:image] or a cube file.")
@click.option("--illuminant", default="D65", show_default=True, help="Illuminant of the colour differences.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), default=None, help="Write the report here.")
@click.option("--device", "device", default=None, help="OpenCL device selector.")
def evaluate(cube, truth, illuminant, json_path, device):
    """Accuracy of a recovered cube (or XYZ map) against the true scene: per pixel, and per patch for a chart."""
    import json

    import numpy as np

    from . import io
    from .evaluate import evaluate_pixels, evaluate_reflectance, evaluate_XYZ
    from .rig.scene import load_scene

    try:
        data, wavelengths, meta = io.read_cube(cube)
    except ValueError as cube_error:
        try:  # a tristimulus recovery: an XYZ map
            data, _, meta = io.read_map(cube, "XYZ")
            wavelengths = None
        except ValueError:
            raise cube_error from None
    height, width = data.shape[:2]
    with _Busy("evaluating"):
        scene = load_scene(truth, height, width)
        pixels = evaluate_pixels(data, scene, wavelengths=wavelengths, illuminant=illuminant, device=device)
    stats = pixels.statistics()
    report = {"cube": str(cube), "truth": scene.name, "illuminant": illuminant,
              "projections": meta.get("projections"), "plan_method": meta.get("plan_method"), "pixels": stats}
    headline = {k: stats[k] for k in stats}
    if scene.masks:
        patch = (evaluate_reflectance(data, wavelengths, scene, illuminant=illuminant) if wavelengths is not None
                 else evaluate_XYZ(data, scene, illuminant=illuminant))
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
    click.echo(f"{basis}: " + ", ".join(f"{names[k]} mean {v['mean']:.4g} max {v['max']:.4g}"
                                        for k, v in headline.items())
               + (f"; {report['projections']} projections" if report["projections"] else ""))
    if json_path:
        from pathlib import Path

        tmp = Path(json_path).with_name(Path(json_path).name + ".tmp")
        tmp.write_text(json.dumps(report, indent=1))
        tmp.replace(json_path)


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
    from .demo import format_tables, run_demo

    result = run_demo(out, rig=rig_path, seed=seed, echo=click.echo, device=device, draws=draws)
    click.echo(format_tables(result))
    click.echo(f"\ndemo finished in {result.seconds:.1f} s; report: {result.out / 'index.html'}")


if __name__ == "__main__":  # pragma: no cover
    main()
