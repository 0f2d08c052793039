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
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np

from .survey_errors import SurveyError

__all__ = ["run_batch", "survey_job", "product_digest", "options_from_dict"]


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
        return "survey" in json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False


def survey_job(job):
    """Run one job (module docstring); returns a plain dict: ``name``, ``out``, ``ok``,
    ``error`` (one line, or None), ``digest``, ``figures`` (survey.json's content) and
    ``wall_s``."""
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
            card = _fly(job["scenario"], int(job["seed"]), out)
            values.setdefault("truth", str(out / "truth.json"))
            values.setdefault("base_station", _beside(card, "base.csv", None, False))
        else:
            card = Path(job["card"])
            if not card.is_file():
                raise SurveyError(f"{card}: no such card image")
        options = options_from_dict(values)
        result = survey_card(card, options)
        write_products(result, out)
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


def run_batch(jobs, *, scheduler=None, workers=2, serial=False):
    """Run ``jobs`` and return their records in the jobs' order (module docstring)."""
    jobs = list(jobs)
    if serial or not jobs:
        return [survey_job(job) for job in jobs]
    from dask.distributed import Client, LocalCluster
    if scheduler is not None:
        try:
            client = Client(scheduler, timeout="10s")
        except (OSError, TimeoutError, ValueError) as error:
            raise SurveyError(f"cannot reach the Dask scheduler at {scheduler}: "
                              f"{error}") from None
        cluster = None
    else:
        if workers < 1:
            raise SurveyError(f"workers must be at least 1, not {workers}")
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               dashboard_address=None)
        client = Client(cluster)
    try:
        futures = client.map(survey_job, jobs, pure=False)
        records = []
        for job, future in zip(jobs, futures):
            try:
                records.append(future.result())
            except Exception as error:      # noqa: BLE001 - a lost worker ends its job only
                out = Path(job["out"])
                records.append({"name": job.get("name") or out.name, "out": str(out),
                                "ok": False, "digest": None, "figures": None, "wall_s": 0.0,
                                "error": f"the Dask worker failed ({type(error).__name__}: "
                                         f"{error})"})
        return records
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
