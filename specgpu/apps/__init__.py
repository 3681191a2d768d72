"""What users touch: the `specgpu` command (`cli`), the demo and its report, the napari viewer and the stream's live
view, and the harness of `specgpu bench` (`bench`). Studies, benchmark scripts and maintenance tools live outside
the package, in the source tree's `tools/`."""
