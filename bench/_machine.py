"""What a benchmark ran on: machine, tool versions and the state of the work tree.

Importing this module takes a snapshot of the work tree and the load average: that is the
state the benchmark started from. :func:`write_report` takes a second snapshot when the
figures are written, records both, and says which paths changed while the benchmark ran
(several people share this tree). :func:`provenance_line` renders a report's provenance as
the one line bench/RESULTS.md carries under each table (``bench/provenance.py`` checks it).
"""

import contextlib
import datetime
import hashlib
import json
import os
import platform
import shlex
import subprocess
import sys
from importlib import metadata
from pathlib import Path


__all__ = ["REPO", "OUTPUTS", "now", "load", "machine", "packages", "command_version",
           "work_tree", "command_line", "scratch_dir", "write_report", "provenance_line",
           "PROVENANCE_PREFIX"]

REPO = Path(__file__).resolve().parent.parent
#: The benchmarks' own outputs: not source that ran, so left out of the source hash (they
#: still appear in ``git status --porcelain`` when modified).
OUTPUTS = ("bench/results/",)
#: Environment variables recorded with the command: they change what code or how it runs.
COMMAND_ENVIRONMENT = ("PYTHONPATH", "NUMBA_NUM_THREADS", "OMP_NUM_THREADS",
                       "MAGLOG_PEERS_PYTHON")
#: How every provenance line in bench/RESULTS.md starts: ``Provenance (<json path>): ...``.
PROVENANCE_PREFIX = "Provenance ("


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


def _git(*args):
    try:
        proc = subprocess.run(["git", *args], cwd=REPO, capture_output=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return proc.stdout if proc.returncode == 0 else None


def _file_digests():
    """{path: sha256 of its bytes in the work tree (None if deleted)} for every tracked
    file and every untracked file git does not ignore, benchmark outputs left out."""
    listing = _git("ls-files", "-z", "--cached", "--others", "--exclude-standard")
    if listing is None:
        return None
    digests = {}
    for name in sorted(set(listing.decode().split("\0")) - {""}):
        if name.startswith(OUTPUTS):
            continue
        path = REPO / name
        if path.is_symlink():
            digests[name] = hashlib.sha256(os.readlink(path).encode()).hexdigest()
        elif path.is_file():
            digests[name] = hashlib.sha256(path.read_bytes()).hexdigest()
        else:
            digests[name] = None                       # tracked, deleted in the work tree
    return digests


def _tree_hash(digests):
    total = hashlib.sha256()
    for name, digest in digests.items():
        total.update(f"{name}\0{digest or '-'}\n".encode())
    return total.hexdigest()


def work_tree():
    """The whole work tree: commit, `git status --porcelain` (every line), and the source
    hash, a sha256 over the path and contents of every tracked and untracked, not ignored
    file as it is on disk (bench/results/ left out)."""
    head = _git("rev-parse", "HEAD")
    status = _git("status", "--porcelain", "--untracked-files=all")
    digests = _file_digests()
    return {
        "commit": head.decode().strip() if head else None,
        "status_porcelain": None if status is None else
        [line for line in status.decode().splitlines() if line],
        "source_sha256": None if digests is None else _tree_hash(digests),
        "source_files": None if digests is None else len(digests),
        "source_sha256_excludes": list(OUTPUTS),
        "_digests": digests,
    }


def command_line(argv):
    """How the script was invoked, relative to the repository."""
    script = Path(sys.argv[0]).resolve()
    try:
        script = script.relative_to(REPO)
    except ValueError:
        pass
    python = Path(os.path.abspath(sys.executable))      # not resolved: the venv's link
    try:
        python = python.relative_to(REPO)
    except ValueError:
        pass
    # Environment that changes what runs (a module path, numba's threads) goes first.
    env = [f"{name}={os.environ[name]}" for name in COMMAND_ENVIRONMENT if name in os.environ]
    return shlex.join([*env, str(python), str(script), *argv])


#: The state the benchmark started from (this module is imported at its start).
_START = {"date": now(), "load": load(), "tree": work_tree()}


def _public(tree):
    return {key: value for key, value in tree.items() if not key.startswith("_")}


def write_report(path, benchmark, argv, load_start, tools, **fields):
    """Write a benchmark's JSON: what ran, on what machine and tree, and its figures.

    ``argv`` is the argument list the script parsed (None: ``sys.argv[1:]``); ``load_start``
    the load average the caller took before measuring (None: the one taken on import)."""
    start, end = _START["tree"], work_tree()
    changed = None
    if start["_digests"] is not None and end["_digests"] is not None:
        changed = sorted(name for name in set(start["_digests"]) | set(end["_digests"])
                         if start["_digests"].get(name, "absent")
                         != end["_digests"].get(name, "absent"))
    report = {
        "benchmark": benchmark,
        "date": _START["date"], "date_end": now(),
        "command": command_line(sys.argv[1:] if argv is None else list(argv)),
        "command_exact": {"argv": [sys.executable, *sys.argv], "cwd": os.getcwd(),
                          "environment": {name: os.environ.get(name)
                                          for name in COMMAND_ENVIRONMENT}},
        "machine": machine(),
        "load_average": {"start": load_start if load_start is not None else _START["load"],
                         "end": load()},
        "tools": tools,
        "work_tree": dict(_public(start),
                          end={"commit": end["commit"],
                               "source_sha256": end["source_sha256"],
                               "changed_during_run": changed}),
        **fields,
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2, default=str) + "\n")
    print(f"written {path}")
    return report


def provenance_line(report, source=None):
    """The one-line provenance of a benchmark report (a dict read from its JSON):

    ``Provenance (<source>): commit abc1234, clean | N uncommitted source paths [and M
    result files] | clean but for M result files (bench/results/), source sha256
    0123456789ab; 2026-11-24T01:30:00+00:00; load 0.42→1.10; `command` ``

    Everything in it comes from the JSON; bench/RESULTS.md carries it under each table."""
    tree = report.get("work_tree", {})
    commit = (tree.get("commit") or "unknown")[:7]
    status = tree.get("status_porcelain")
    if status is None:
        state = "uncommitted state not recorded"
    elif not status:
        state = "clean"
    else:
        # Paths under OUTPUTS are earlier benchmarks' results, outside the source hash.
        source_paths = [line for line in status
                        if not any(line[3:].startswith(out) for out in OUTPUTS)]
        outputs = len(status) - len(source_paths)
        if source_paths:
            state = (f"{len(source_paths)} uncommitted source "
                     f"path{'s' if len(source_paths) != 1 else ''}")
            if outputs:
                state += f" and {outputs} result file{'s' if outputs != 1 else ''}"
        else:
            state = (f"clean but for {outputs} result file{'s' if outputs != 1 else ''} "
                     f"({', '.join(OUTPUTS)})")
    digest = tree.get("source_sha256")
    source_hash = f"source sha256 {digest[:12]}" if digest else "no source hash"
    end = tree.get("end") or {}
    changed = end.get("changed_during_run")
    notes = []
    if changed:
        notes.append(f"{len(changed)} path{'s' if len(changed) != 1 else ''} changed during "
                     f"the run")
    if end.get("commit") and tree.get("commit") and end["commit"] != tree["commit"]:
        notes.append(f"HEAD moved to `{end['commit'][:7]}` during the run")
    during = f" ({'; '.join(notes)})" if notes else ""
    loads = report.get("load_average") or {}

    def one(value):
        return "?" if not value else f"{value[0]:.2f}"
    where = f" ({source})" if source else ""
    return (f"Provenance{where}: commit `{commit}`, {state}, {source_hash}"
            f"{during}; {report.get('date', '?')}; load {one(loads.get('start'))}→"
            f"{one(loads.get('end'))}; `{report.get('command', '?')}`")


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
