"""``specgpu bench``: the kernels' throughput against NumPy / colour-science baselines, or the stream's."""

from __future__ import annotations

import click

from specgpu.apps.bench.kernels import run_bench
from specgpu.apps.bench.sizes import parse_sizes
from specgpu.apps.bench.stream import run_stream_bench
from specgpu.apps.cli.options import command, no_clash


def sizes_option(text, option, one=False):
    """Image sizes from ``text`` (``one``: the single size); a bad one is a usage error (exit 2) naming ``option``
    and the token."""
    try:
        if one:
            (width, height), = parse_sizes(text)
            return width, height
        return parse_sizes(text)
    except ValueError as error:  # before any device work
        raise click.BadParameter(str(error), param_hint=option) from error


@command()
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
@click.option("--stream-cases", default="fused, sigma, sigma_rms, white, cube, paced, overload, equality",
              show_default=True,
              help="With --stream: comma-separated cases to run (also dE_sigma; linear and denoise: the cost of "
                   "--denoise; motion: the rate with --motion global beside the static one; motion_flow: the rate "
                   "with --motion flow; static and full: best quality without and with --motion global --denoise "
                   "--white-roi, and their ratio; paced_full: full at the camera's 200 fps).")
@click.option("--stream-rounds", type=click.IntRange(min=1), default=1, show_default=True,
              help="With --stream: interleaved rounds of the sustained cases (fused, sigma, sigma_rms, white, "
                   "dE_sigma, static, full); "
                   "each reports its median round.")
def bench(device, json_path, sizes, repeats, stream, stream_size, stream_seconds, paced_seconds, stream_cases,
          stream_rounds):
    """Throughput of each kernel against NumPy / colour-science baselines measured in the same run."""
    no_clash([("--json", json_path)])
    if not stream:
        run_bench(sizes=sizes_option(sizes, "--sizes"), device=device, repeats=repeats, json_path=json_path,
                  echo=click.echo)
        return
    width, height = sizes_option(stream_size, "--stream-size", one=True)
    run_stream_bench(seconds=stream_seconds, paced_seconds=paced_seconds, overload_seconds=stream_seconds,
                     width=width, height=height, device=device, json_path=json_path, echo=click.echo,
                     cases=tuple(c.strip() for c in stream_cases.split(",") if c.strip()), rounds=stream_rounds)
