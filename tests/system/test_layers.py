"""The rig model never imports the capture package."""

import subprocess
import sys


def test_rig_modules_do_not_import_capture():
    code = ("import sys\n"
            "import specgpu.rig, specgpu.rig.twin, specgpu.rig.light, specgpu.rig.camera, specgpu.rig.config\n"
            "import specgpu.rig.scene, specgpu.rig.spectroradiometer\n"
            "from specgpu.rig.twin import measure_snr\n"
            "bad = sorted(m for m in sys.modules if m.startswith('specgpu.capture'))\n"
            "print(','.join(bad))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_programmable_light_is_a_light_source_once_capture_is_loaded():
    from specgpu.capture.driver import LightSource
    import specgpu.capture.twin  # noqa: F401  (registers the twin's light)
    from specgpu.rig.light import ProgrammableLight

    assert isinstance(ProgrammableLight(), LightSource)
