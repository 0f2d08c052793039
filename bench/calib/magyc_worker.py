"""Runs the `magyc` package's ellipsoid fits for bench/calib/run.py, in the peers' venv.

magyc 1.0.0 pins numpy < 2 and pulls gtsam and jax, so it lives in its own environment
(`make bench-peers` makes `.venv-peers`); this script is the only code that runs there.
Input: an .npz of (N, 3) sample arrays. Output (stdout): JSON, per array and per method,
the hard-iron vector, the soft-iron matrix, the calibrated field magyc returned (first
rows) and the best-of-3 time, or the error.
"""

import json
import sys
import time
import warnings

import numpy as np


def main(path):
    import magyc
    data = np.load(path)
    out = {"magyc": getattr(magyc, "__version__", None), "numpy": np.__version__,
           "cases": {}}
    for key in data.files:
        b = data[key]
        case = {}
        for name in ("ellipsoid_fit", "ellipsoid_fit_fang"):
            fn = getattr(magyc, name)
            times, result, error = [], None, None
            for _ in range(3):
                start = time.perf_counter()
                try:
                    with warnings.catch_warnings(record=True) as caught:
                        warnings.simplefilter("always")
                        result = fn(b.copy())
                except Exception as exc:                   # a failure is a result here
                    error = f"{type(exc).__name__}: {exc}"
                    break
                times.append(time.perf_counter() - start)
            if error:
                case[name] = {"error": error}
                continue
            hard, soft, calibrated = result
            case[name] = {"hard_iron": np.asarray(hard, float).tolist(),
                          "soft_iron": np.asarray(soft, float).tolist(),
                          "calibrated_head": np.asarray(calibrated, float)[:50].tolist(),
                          "seconds": min(times),
                          "warnings": sorted({str(w.message) for w in caught})}
        out["cases"][key] = case
    json.dump(out, sys.stdout)


if __name__ == "__main__":
    main(sys.argv[1])
