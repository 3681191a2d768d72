"""The harness of ``specgpu bench``: the kernels against NumPy / colour-science baselines (:mod:`.kernels`, with
the denoiser's case in :mod:`.denoise`), the stream on a replayed twin recording (:mod:`.stream`) and the image
sizes both take (:mod:`.sizes`)."""
