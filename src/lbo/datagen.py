"""`python -m lbo.datagen data=<smoke|quick|paper>`: generate (or reuse) the three data sets;
`data=logs data.train=[...] ...`: check and cache a user's logs as them."""

from __future__ import annotations

import sys
import time

from omegaconf import DictConfig

from lbo.core.cli import entry


def generate(cfg: DictConfig) -> str:
    """Generate the sets for ``cfg``, print the summary and return the folder."""
    from lbo.logs import sets as logs
    from lbo.sim.datasets import build, data_lock, figures, spec_from_cfg, summary

    if logs.is_logs(cfg):
        return _logs(cfg)
    spec = spec_from_cfg(cfg)
    start = time.perf_counter()
    folder, sets, cached = build(spec)
    if cfg.get("figures", True):
        with data_lock(folder):
            figures(spec, sets, folder)
    s = summary(spec, sets)
    took = time.perf_counter() - start
    print(f"{'reused cached' if cached else 'generated'} data sets '{spec.name}' in {took:.1f} s")
    print(f"  train: {s['rows_train']:,} rows, friction-circle coverage {s['coverage']:.1%} "
          f"of {spec.train['grid']}x{spec.train['grid']} cells inside {spec.train['radius_g']} g")
    print(f"  val:   {s['rows_val']:,} rows, {s['scored_val']:,} scored")
    print(f"  test:  {s['rows_test']:,} rows, {s['scored_test_per_alpha']:,} scored points x "
          f"{len(spec.alphas)} alpha levels = {s['scored_test']:,} scored rows")
    for n in ("train", "val", "test"):
        v, p = s[f"V_{n}"], s[f"psi_{n}"]
        print(f"  {n:5s}  V in [{v[0]:.1f}, {v[1]:.1f}] m/s, psi in [{p[0]:.2f}, {p[1]:.2f}] rad")
    print(f"datasets: {folder}")
    return str(folder)


def _logs(cfg: DictConfig) -> str:
    """``data=logs``: check and cache a user's logs as the three sets; print what they hold."""
    from lbo.logs import sets as logs

    spec = logs.spec_from_cfg(cfg)
    start = time.perf_counter()
    folder, sets, cached = logs.build(spec)
    took = time.perf_counter() - start
    print(f"{'reused checked' if cached else 'checked and cached'} logs in {took:.1f} s")
    print("\n".join(logs.summary(folder, sets, spec.vehicle.dt)))
    print(f"datasets: {folder}")
    return str(folder)


main = entry("datagen", generate)


if __name__ == "__main__":
    sys.exit(main())
