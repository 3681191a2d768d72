"""Re-measure the figures the documentation's accuracy and performance pages show.

Each result is one command that writes JSON; this script runs it and stores its JSON under ``docs/results/``
together with the command as written, the date, the machine and its load, so the page built from the file
(``docs/_ext/results.py``) says where every figure comes from. Run from the repository root::

    python docs/results/refresh.py            # every result
    python docs/results/refresh.py bench      # one of them
"""

from __future__ import annotations

import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]

#: Each result: its file name (without ``.json``) -> the command that measures it, ``OUT`` standing for the JSON
#: file the command writes. Small sizes, so that a refresh takes a few minutes on a laptop.
COMMANDS = {
    "bench": "specgpu bench --sizes 320x240 --json OUT",
    "accuracy": "python tools/studies/accuracy_study.py --small --runs 3 --json OUT",
}


def machine() -> dict:
    """The machine a figure was measured on: CPU model, cores, operating system and Python."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": model, "cores": os.cpu_count(), "system": platform.platform(terse=True),
            "python": platform.python_version()}


def load_average() -> float | None:
    try:
        return round(os.getloadavg()[0], 2)
    except OSError:
        return None


def refresh(name: str) -> Path:
    """Run result ``name``'s command and write ``docs/results/NAME.json``; returns its path."""
    command = COMMANDS[name]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / f"{name}.json"
        words = shlex.split(command.replace("OUT", str(out)))
        argv = ([sys.executable, "-m", "specgpu", *words[1:]] if words[0] == "specgpu"
                else [sys.executable, *words[1:]])
        started, load_start, t0 = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), load_average(), time.time()
        subprocess.run(argv, cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
        record = {"name": name, "command": command, "date_utc": started, "wall_s": round(time.time() - t0, 1),
                  "machine": machine(), "load_avg_1min": {"start": load_start, "end": load_average()},
                  "result": json.loads(out.read_text())}
    path = HERE / f"{name}.json"
    path.write_text(json.dumps(record, indent=1, default=float) + "\n")
    return path


def main(argv: list[str]) -> int:
    names = argv or list(COMMANDS)
    unknown = [n for n in names if n not in COMMANDS]
    if unknown:
        print(f"refresh.py: unknown result {unknown[0]!r}; choose from {', '.join(COMMANDS)}", file=sys.stderr)
        return 2
    for name in names:
        print(f"{name}: {COMMANDS[name]}", flush=True)
        print(f"  wrote {refresh(name).relative_to(ROOT)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
