#!/usr/bin/env python3
"""Great-circle distances: pyproj.Geod (on the sphere of EARTH_RADIUS_KM) against the numpy
haversine, per call, at the sizes the code uses (1: a prior vs a point; 50: a query's candidates;
1,000: a map's submap centroids; 100,000: build-time calibration). Prints a table; the
docstring of vlm_vpr_ros/geodesy.py quotes it.

    python benchmarks/bench_geodesy.py [--repeat R]
"""

from __future__ import annotations

import argparse
import timeit

import numpy as np

from vlm_vpr_ros.geodesy import EARTH_RADIUS_KM, _numpy_haversine_km, _SPHERE


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeat", type=int, default=5, help="best of R timings (default 5)")
    args = p.parse_args(argv)
    rng = np.random.default_rng(0)
    print(f"{'pairs':>8} {'numpy haversine us':>20} {'pyproj.Geod us':>16} {'max diff m':>12}")
    for n in (1, 50, 1000, 100_000):
        la1, la2 = rng.uniform(-89, 89, (2, n))
        lo1, lo2 = rng.uniform(-180, 180, (2, n))
        if n == 1:
            la1, lo1, la2, lo2 = (float(v[0]) for v in (la1, lo1, la2, lo2))
        number = max(1, 20_000 // n)
        t_np = min(timeit.repeat(lambda: _numpy_haversine_km(la1, lo1, la2, lo2),
                                 number=number, repeat=args.repeat)) / number
        t_geod = min(timeit.repeat(lambda: _SPHERE.inv(lo1, la1, lo2, la2),
                                   number=number, repeat=args.repeat)) / number
        diff = np.max(np.abs(np.asarray(_numpy_haversine_km(la1, lo1, la2, lo2)) * 1000.0
                             - np.asarray(_SPHERE.inv(lo1, la1, lo2, la2)[2])))
        print(f"{n:>8} {t_np * 1e6:>20.1f} {t_geod * 1e6:>16.1f} {diff:>12.2e}")
    print(f"(sphere radius {EARTH_RADIUS_KM} km)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
