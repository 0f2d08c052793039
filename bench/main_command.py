"""Wall time of the README's main command on a fresh clone.

Clones the repository's HEAD into a new folder (``git clone``, so only what is committed),
runs ``make setup`` (the venv, the install, the tool links: timed apart) and then
``make run`` (the main job on the built-in scenario, its first Verilator build included),
and records both times, their exit status and the summary's verdict.

Run from the repository root: ``.venv/bin/python bench/main_command.py``. Pip's cache is
the user's; a set-up with an empty cache takes longer (the download).
"""

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.dont_write_bytecode = True
from _machine import REPO, load, packages, write_report

DEFAULT_OUTPUT = Path(__file__).resolve().parent / "results" / "main_command.json"


def _timed(command, cwd, log):
    start = time.perf_counter()
    with open(log, "w") as out:
        done = subprocess.run(command, cwd=cwd, stdout=out, stderr=subprocess.STDOUT)
    return time.perf_counter() - start, done.returncode


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    parser.add_argument("--keep", action="store_true", help="keep the clone")
    args = parser.parse_args(argv)
    load_start = load()
    folder = Path(tempfile.mkdtemp(prefix="main-command-"))
    clone = folder / "maglog"
    subprocess.run(["git", "clone", "-q", str(REPO), str(clone)], check=True)
    commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=clone, check=True,
                            capture_output=True, text=True).stdout.strip()
    setup_s, setup_exit = _timed(["make", "setup"], clone, folder / "setup.log")
    run_s, run_exit = _timed(["make", "run"], clone, folder / "run.log")
    summary = clone / "build" / "run" / "report" / "summary.json"
    verdict = "no summary"
    if summary.exists():
        verdict = "all checks pass" if json.loads(summary.read_text())["ok"] else \
            "checks failed"
    result = {"commit": commit, "clone": "git clone of the repository, pip cache warm",
              "setup_s": setup_s, "setup_exit": setup_exit, "run_s": run_s,
              "run_exit": run_exit, "verdict": verdict}
    write_report(args.output, "main_command", argv, load_start, packages("pip"),
                 result=result)
    if not args.keep:
        shutil.rmtree(folder, ignore_errors=True)
    else:
        print(f"kept {folder}")
    return 0 if setup_exit == 0 and run_exit == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
