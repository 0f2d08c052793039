"""Many survey reductions at once: cards, or scenario seeds flown through the logger first.

A job is a plain dict (so that it pickles to any Dask worker):

``{"card": PATH, "out": DIR, "options": {...}}``
    reduce one card image (:func:`maglog.calib.survey.survey_card`) into ``DIR``;
``{"scenario": NAME_OR_PATH, "seed": N, "out": DIR, "options": {...}}``
    build the scenario with that seed, run it through the logger on the ``model`` backend
    into ``DIR/card.img`` (truth and base station beside it), then reduce that card.

:func:`run_batch` runs the jobs serially in this process, on a local Dask cluster
(``workers`` processes of one thread each: the default), or on a running Dask scheduler
(``scheduler="tcp://host:8786"``). Every job is deterministic (the calibration's swarm is
seeded, the rest has no randomness), so the three give the same products; each result
carries a digest of its map and samples to show it (:func:`product_digest`).
A job that fails returns its one-line error instead of products; the others go on.
Nothing is printed: ``on_done(record, done, total)`` hears of each job as it finishes (in
the order they finish), and a job run in this process tells ``stages(label, seconds)`` of
each of its stages as it starts (``seconds`` None) and ends: :data:`FLY` (scenario jobs),
the reduction's own (:data:`maglog.calib.survey.STAGES`), :data:`WRITE`.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np

from .survey_errors import SurveyError

__all__ = ["run_batch", "survey_job", "product_digest", "options_from_dict",
           "probe_scheduler", "FLY", "WRITE"]

#: A job's stages before and after the reduction's own.
FLY = "flying the scenario through the logger (model backend)"
WRITE = "writing the products (grids, plots, report)"


def options_from_dict(values):
    from .survey import SurveyOptions
    values = dict(values or {})
    for key in ("band", "box"):
        if values.get(key) is not None:
            values[key] = tuple(values[key])
    return SurveyOptions(**values)


def product_digest(result):
    """SHA-256 of what a reduction produced: the grid's values and the levelled samples
    (float64 bytes), so two runs can be compared exactly."""
    h = hashlib.sha256()
    for array in (result.grid["anomaly"].values, result.t, result.compensated,
                  result.levelled):
        h.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    return h.hexdigest()


def _beside(card, name, given, disabled):
    if disabled:
        return None
    if given is not None:
        return given
    candidate = Path(card).parent / name
    return str(candidate) if candidate.is_file() else None


def _is_survey_truth(path):
    try:
        truth = json.loads(Path(path).read_text(encoding="utf-8"))
        return isinstance(truth, dict) and "survey" in truth
    except (OSError, ValueError):
        return False


def _timed(stages, label, call, *args):
    """``call(*args)``, its start and end told to ``stages`` (if any)."""
    if stages is None:
        return call(*args)
    stages(label, None)
    started = time.perf_counter()
    value = call(*args)
    stages(label, time.perf_counter() - started)
    return value


def survey_job(job, stages=None):
    """Run one job (module docstring); returns a plain dict: ``name``, ``out``, ``ok``,
    ``error`` (one line, or None), ``digest``, ``figures`` (survey.json's content) and
    ``wall_s``. ``stages``: see the module docstring."""
    from .card import CardError
    from .pipeline import CalibrationError
    from .survey import survey_card, summary, write_products
    started = time.perf_counter()
    out = Path(job["out"])
    name = job.get("name") or out.name
    record = {"name": name, "out": str(out), "ok": False, "error": None, "digest": None,
              "figures": None}
    try:
        values = dict(job.get("options") or {})
        if "scenario" in job:
            card = _timed(stages, FLY, _fly, job["scenario"], int(job["seed"]), out)
            values.setdefault("truth", str(out / "truth.json"))
            values.setdefault("base_station", _beside(card, "base.csv", None, False))
        else:
            card = Path(job["card"])
            if not card.is_file():
                raise SurveyError(f"{card}: no such card image")
        options = options_from_dict(values)
        result = survey_card(card, options, progress=stages)
        _timed(stages, WRITE, write_products, result, out)
        record.update(ok=True, digest=product_digest(result), figures=summary(result))
    except (SurveyError, CardError, CalibrationError) as error:
        record["error"] = str(error)
    except OSError as error:
        record["error"] = f"{error.filename or out}: {error.strerror or error}"
    except Exception as error:           # noqa: BLE001 - one job's bug must not end a batch
        record["error"] = (f"unexpected {type(error).__name__} (a bug in maglog; please "
                           f"report it with this card): {error}")
    record["wall_s"] = time.perf_counter() - started
    return record


def _fly(scenario, seed, out):
    """The scenario with ``seed`` through the logger (model backend) into ``out/card.img``."""
    import contextlib
    import dataclasses
    import io
    from ..cli.run import RunError, simulate
    from ..sim.stimulus.config import ScenarioError, load_scenario
    try:
        loaded = dataclasses.replace(load_scenario(scenario), seed=seed)
        stimulus = loaded.build()
    except (ScenarioError, OSError) as error:
        raise SurveyError(str(error)) from None
    card = out / "card.img"
    try:
        with contextlib.redirect_stderr(io.StringIO()):
            simulate(stimulus, card, backend="model", build_dir=out / "build",
                     progress=False)
    except RunError as error:
        raise SurveyError(str(error)) from None
    return card


#: Seconds to connect to a scheduler and to wait for its first bytes (a Dask scheduler
#: writes its handshake as soon as a connection is made); the largest handshake believed.
PROBE_TIMEOUT_S = 5.0
MAX_HANDSHAKE_BYTES = 1 << 26


def probe_scheduler(address, timeout=PROBE_TIMEOUT_S):
    """Check that a Dask scheduler answers at ``address`` (``tcp://host:port``, ``host:port``
    or ``tls://host:port``) before Dask is given it, and return the address for Dask. A
    Dask scheduler writes its handshake (a little-endian 8-byte length, then that many
    bytes) as soon as a connection is made: a port that says nothing (an HTTP server), one
    that says something else (an SSH banner, read as a length of exabytes) or none at all
    is refused in one line, not a hang or an out-of-memory."""
    import socket
    import struct
    text = str(address).strip()
    scheme, sep, rest = text.partition("://")
    if not sep:
        scheme, rest = "tcp", text
    if scheme not in ("tcp", "tls"):
        raise SurveyError(f"--scheduler {text[:80]!r}: give a running Dask scheduler's "
                          "address as tcp://HOST:PORT (or tls://HOST:PORT); "
                          f"{scheme[:20]}:// is not one")
    host, colon, port_text = rest.rpartition(":")
    host = host.strip("[]")
    if not colon or not host or not port_text.isdigit() or not 0 < int(port_text) < 65536:
        raise SurveyError(f"--scheduler {text[:80]!r}: expected tcp://HOST:PORT with a port "
                          "from 1 to 65535 (tcp://127.0.0.1:8786)")
    port = int(port_text)
    if scheme == "tls":
        return text                        # a TLS listener waits for our hello: Dask's job
    try:
        with socket.create_connection((host, port), timeout=timeout) as sock:
            sock.settimeout(timeout)
            head = b""
            while len(head) < 8:
                chunk = sock.recv(8 - len(head))
                if not chunk:
                    break
                head += chunk
    except socket.timeout:
        raise SurveyError(f"no Dask scheduler at {text[:80]}: something accepts the "
                          f"connection but says nothing within {timeout:g} s (another "
                          "service, such as an HTTP server?)") from None
    except OSError as error:
        raise SurveyError(f"cannot reach the Dask scheduler at {text[:80]}: "
                          f"{error.strerror or error}") from None
    except (UnicodeError, ValueError) as error:     # a host name no resolver takes
        raise SurveyError(f"cannot reach the Dask scheduler at {text[:80]}: {host[:40]!r} "
                          f"is not a host name ({error})") from None
    if len(head) < 8:
        raise SurveyError(f"no Dask scheduler at {text[:80]}: the connection was closed "
                          "without a handshake")
    length, = struct.unpack("<Q", head)
    if not 0 < length <= MAX_HANDSHAKE_BYTES:
        raise SurveyError(f"no Dask scheduler at {text[:80]}: another service answers there "
                          f"(it began {head!r})")
    return f"tcp://{rest}"


def run_batch(jobs, *, scheduler=None, workers=2, serial=False, on_done=None, stages=None):
    """Run ``jobs`` and return their records in the jobs' order (module docstring;
    ``stages`` is told of the stages of jobs run in this process, ``serial``)."""
    jobs = list(jobs)
    if serial or not jobs:
        records = []
        for job in jobs:
            records.append(survey_job(job, stages))
            if on_done is not None:
                on_done(records[-1], len(records), len(jobs))
        return records
    from dask.distributed import Client, LocalCluster
    if scheduler is not None:
        address = probe_scheduler(scheduler)
        try:
            client = Client(address, timeout="10s")
        except Exception as error:          # noqa: BLE001 - whatever Dask raises, one line
            raise SurveyError(f"cannot use the Dask scheduler at {scheduler}: "
                              f"{type(error).__name__}: {str(error)[:200]}") from None
        cluster = None
    else:
        if workers < 1:
            raise SurveyError(f"workers must be at least 1, not {workers}")
        try:
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                   dashboard_address=None)
        except Exception as error:          # noqa: BLE001 - whatever Dask raises, one line
            raise SurveyError(f"cannot start a local Dask cluster of {workers} workers "
                              f"({type(error).__name__}: {str(error)[:200]}); run the jobs "
                              "one after another with --serial") from None
        client = Client(cluster)
    try:
        from dask.distributed import as_completed
        futures = client.map(survey_job, jobs, pure=False)
        index = {future.key: k for k, future in enumerate(futures)}
        records = [None] * len(jobs)
        for done, future in enumerate(as_completed(futures), 1):
            k = index[future.key]
            try:
                records[k] = future.result()
            except Exception as error:      # noqa: BLE001 - a lost worker ends its job only
                out = Path(jobs[k]["out"])
                records[k] = {"name": jobs[k].get("name") or out.name, "out": str(out),
                              "ok": False, "digest": None, "figures": None, "wall_s": 0.0,
                              "error": f"the Dask worker failed ({type(error).__name__}: "
                                       f"{error})"}
            if on_done is not None:
                on_done(records[k], done, len(jobs))
        return records
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
