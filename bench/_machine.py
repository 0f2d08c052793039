"""What a benchmark ran on: machine, tool versions and the state of the work tree."""

import contextlib
import datetime
import hashlib
import os
import platform
import subprocess
import sys
from importlib import metadata
from pathlib import Path


__all__ = ["REPO", "now", "load", "machine", "packages", "command_version", "work_tree",
           "command_line", "scratch_dir", "write_report"]

REPO = Path(__file__).resolve().parent.parent


def now():
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def load():
    """1, 5 and 15 minute load averages: other work on a 2-core machine skews the timings."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def _cpu_model():
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _memory_total():
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return f"{int(line.split()[1]) / 2**20:.1f} GiB"
    except OSError:
        pass
    return "unknown"


def machine():
    """CPU count (as `nproc` sees it), CPU model, memory, OS and Python."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:
        cpus = os.cpu_count()
    return {
        "nproc": cpus,
        "cpu_model": _cpu_model(),
        "memory_total": _memory_total(),
        "platform": platform.platform(),
        "python": platform.python_version(),
    }


def packages(*names):
    """Installed versions of Python distributions (None when missing)."""
    found = {}
    for name in names:
        try:
            found[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            found[name] = None
    return found


def command_version(*argv):
    """First non-empty output line of a `--version`-style command, or None."""
    try:
        proc = subprocess.run(argv, capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return None
    for line in (proc.stdout + proc.stderr).splitlines():
        if line.strip():
            return line.strip()
    return None


def work_tree():
    """Commit and uncommitted changes of the gateware and simulation sources measured."""
    def git(*args):
        try:
            return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True,
                                  timeout=30).stdout
        except (OSError, subprocess.TimeoutExpired):
            return ""
    changed = [line for line in git("status", "--porcelain", "--", "hw", "sim").splitlines()
               if line]
    # Identifies the uncommitted state: the diff of tracked files plus untracked contents.
    digest = hashlib.sha256(git("diff", "HEAD", "--", "hw", "sim").encode())
    for line in changed:
        if line.startswith("??"):
            path = REPO / line[3:]
            for file in sorted(path.rglob("*") if path.is_dir() else [path]):
                if file.is_file() and "__pycache__" not in file.parts:
                    digest.update(file.read_bytes())
    return {"commit": git("rev-parse", "HEAD").strip() or None,
            "uncommitted_hw_sim": changed,
            "uncommitted_sha256": digest.hexdigest()[:16] if changed else None}


def command_line(argv):
    """How the script was invoked, relative to the repository."""
    script = Path(sys.argv[0]).resolve()
    try:
        script = script.relative_to(REPO)
    except ValueError:
        pass
    python = Path(sys.executable)
    try:
        python = python.relative_to(REPO)
    except ValueError:
        pass
    return " ".join([str(python), str(script), *argv])


def write_report(path, benchmark, argv, load_start, tools, **fields):
    """Write a benchmark's JSON: what ran, on what machine and tree, and its figures."""
    import json
    import sys
    report = {
        "benchmark": benchmark, "date": now(),
        "command": command_line(sys.argv[1:] if argv is None else argv),
        "machine": machine(), "load_average": {"start": load_start, "end": load()},
        "tools": tools, "work_tree": work_tree(), **fields,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2, default=str) + "\n")
    print(f"written {path}")


@contextlib.contextmanager
def scratch_dir(prefix, keep=False):
    """A temporary work directory, removed afterwards unless ``keep`` (then its path is
    printed)."""
    import shutil
    import tempfile
    path = Path(tempfile.mkdtemp(prefix=prefix))
    try:
        yield path
    finally:
        if keep:
            print(f"work directory kept: {path}", file=sys.stderr)
        else:
            shutil.rmtree(path, ignore_errors=True)
