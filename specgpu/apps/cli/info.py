"""``specgpu info`` and ``specgpu selftest``: what this machine offers (OpenCL devices, USB devices) and whether
its device computes every kernel right."""

from __future__ import annotations

import click

from specgpu.apps.cli.options import command
from specgpu.engine.runtime import describe, list_devices, select_device
from specgpu.engine.selftest import run_selftest
from specgpu.hardware.usb import list_usb_devices

_SELECTOR = "Device selector: 'P:D' indices or a name substring."


def device_lines(device):
    """One line per OpenCL device: selector, name, type and platform, ``*`` marking the one ``device`` picks."""
    chosen = select_device(device)
    return [f"{'*' if d.device.int_ptr == chosen.int_ptr else ' '} {d.selector}  {d.name.strip()}  "
            f"[{d.type}, {d.platform.strip()}]" for d in list_devices()]


def usb_lines():
    """The USB devices found, naming those specgpu drives."""
    found = list_usb_devices()
    lines = [f"USB devices: {len(found)}" + ("" if found else " (none)")]
    for dev in found:
        known = f"  <- {dev.description} ({dev.backend})" if dev.backend else ""
        lines.append(f"  {dev.vendor_id:04x}:{dev.product_id:04x} bus {dev.bus} address {dev.address}{known}")
    return lines


@command()
@click.option("--device", "device", default=None, help=_SELECTOR)
@click.option("--devices", "devices_only", is_flag=True,
              help="List only the OpenCL devices, one a line: selector, name, type (* the one chosen).")
@click.option("--usb", is_flag=True,
              help="Also list the USB devices found, naming those specgpu drives (DLPC900 light, USB3 Vision "
                   "camera, Ocean spectrometer, a Teensy or Arduino LED controller board, the OL490 when "
                   "SPECGPU_OL490_USB gives its VID:PID).")
def info(device, devices_only, usb):
    """OpenCL platforms and devices, the one chosen, and versions; --devices: the OpenCL devices alone; --usb:
    the USB devices too."""
    click.echo("\n".join(device_lines(device)) if devices_only else describe(device))
    if usb:
        click.echo("\n".join(usb_lines()))


@command()
@click.option("--device", "device", default=None, help=_SELECTOR)
@click.option("--verbose", "-v", is_flag=True, help="Print the error figures of every case.")
def selftest(device, verbose):
    """Run the kernel regression suite (golden set) on this machine's device; exit 1 if any kernel fails."""
    report = run_selftest(device=device)
    click.echo(report.format(verbose=verbose))
    if not report.passed:
        raise click.ClickException(f"selftest failed on {report.device}: {', '.join(report.failed_kernels())}")
