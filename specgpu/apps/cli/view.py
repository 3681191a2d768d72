"""``specgpu view``: a napari viewer on a cube, map, sequence folder or recording (the optional viewer extra)."""

from __future__ import annotations

import importlib.util

import click

from specgpu.apps.cli.options import command
from specgpu.apps.viewer_layers import motion_note
from specgpu.apps.viewer_widget import open_viewer


@command()
@click.argument("path", type=click.Path(exists=True))
def view(path):
    """Open a cube or map (.exr, .npz, ENVI .hdr), a sequence folder or a zarr recording in napari, with the
    spectrum widget (needs the viewer extra: pip install 'specgpu[viewer]')."""
    if importlib.util.find_spec("napari") is None:
        raise click.ClickException("specgpu view needs napari: pip install 'specgpu[viewer]'")
    note = motion_note(path)
    if note:
        click.echo(note, err=True)
    open_viewer(path)
