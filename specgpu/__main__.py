"""``python -m specgpu``: the ``specgpu`` command, for subprocess drills and machines without the script."""

from specgpu.apps.cli import main

if __name__ == "__main__":
    main()
