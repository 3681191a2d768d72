"""The physical system, modelled: light source, camera, scene and the synchronous twin."""
