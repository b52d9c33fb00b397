"""`make reproduce SCALE=paper|quick [STUDY=paper|dynamic|all]`: the paper's study from one
command, resumable.

    python -m lbo.reproduce scale=quick [study=paper|dynamic|all]

Stages: 1 data, 2 tune (CNN and LSTM at N=20), 3 train the 8 observers with the tuned
parameters, the robust observer (``experiment=robust``, beyond the paper) with the learned
peers trained as it is (``peers``: KalmanNet and Split-KalmanNet at paper scale), the observers of
a car that slips (``experiment=dynamic`` on ``data=dynamic`` and ``dynamic_drift``, with the
black-box and the learned peers on the first, ``dynamic_blackbox``, ``dynamic_peers``; scored
by their own runs on their own test sets), 4 evaluate the classical observers, 5 write the
report. A rerun reuses the
cached data sets, the Optuna studies (only missing trials run), the MLflow runs that
finished with the same config (``resume=true``) and the classical table, and redoes only
what is missing.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

import numpy as np
import pandas as pd
from hydra import compose
from omegaconf import DictConfig

from lbo.core.atomic import write_text
from lbo.core.checks import integer, require
from lbo.core.cli import entry, ready_launcher, respell
from lbo.core.errors import LboError
from lbo.core.paths import store_overrides
from lbo.filters import classical
from lbo.learn.eta import Eta, duration, plan
from lbo.learn.jobs import DYNAMIC, LITERAL, ROBUST, Job, parts, train_jobs
from lbo.tracking.runs import check_store, run_artifact

STAGES = ("data", "tune", "train", "evaluate", "report")


class Stages:
    """Banners, progress and timings; the timings persist in ``stages.json``."""

    def __init__(self, folder: Path) -> None:
        self.path = folder / "stages.json"
        self.record: dict[str, dict] = (json.loads(self.path.read_text())
                                        if self.path.is_file() else {})

    def run(self, i: int, name: str, what: str, fn: Callable[[], tuple[Any, str]]) -> Any:
        print(f"\n==> [{i}/{len(STAGES)}] {name}: {what}", flush=True)
        start = time.perf_counter()
        result, status = fn()
        seconds = time.perf_counter() - start
        prev = self.record.get(name, {})
        if status == "reused" and prev.get("seconds") is not None:
            stage = {"status": "reused", "seconds": prev["seconds"], "check_seconds": seconds}
        else:
            stage = {"status": status, "seconds": seconds}
        self.record[name] = stage
        write_text(self.path, json.dumps(self.record, indent=1))
        print(f"<== [{i}/{len(STAGES)}] {name}: {status} in {seconds:.1f} s", flush=True)
        return result


def reproduce(cfg: DictConfig) -> Path:
    """Run the five stages for ``cfg.scale``; return the report folder."""
    check_reproduce(cfg)
    scale, out = cfg.scale, Path(cfg.report_dir)
    stages = Stages(out)
    t0 = time.perf_counter()
    folder = stages.run(1, "data", f"generate the {scale} data sets (or reuse them)",
                        lambda: stage_data(cfg))
    paper, dynamic = parts(cfg)
    models = list(cfg.models) if paper else []  # tuned for the paper's observers only
    tuned = stages.run(2, "tune", f"{' and '.join(m.upper() for m in models) or 'nothing'} "
                       f"at N=20, {cfg.trials} Optuna trials each",
                       lambda: stage_tune(cfg, out, models))
    jobs = train_jobs(cfg, out)
    runs = stages.run(3, "train", (f"{len(models) * len(cfg.windows)} observers "
                      f"({', '.join(models)} x N={list(cfg.windows)}) with the tuned "
                      "parameters" + (", and the robust observer" if cfg.robust else "")
                      + (f", the paper's protocol ({', '.join(cfg.literal)})"
                         if cfg.literal else "") if paper else "")
                      + (f"{', and' if paper else ''} on a car that slips "
                         f"({', '.join(cfg.dynamic_study)})"
                         if dynamic and cfg.dynamic_study else "")
                      + (f", through hydra/launcher={cfg.launcher}" if cfg.launcher else ""),
                      lambda: stage_train(cfg, out, jobs))
    table = stages.run(4, "evaluate", f"classical observers ({', '.join(cfg.classical)}) on "
                       "the test grid; the learned ones were scored by their runs",
                       lambda: stage_classical(cfg, out, folder))
    stages.run(5, "report", f"tables and figures in {out}",
               lambda: stage_report(cfg, out, folder, tuned, runs, table, stages.record, jobs))
    print(f"\nreport: {out / 'report.md'}  ({time.perf_counter() - t0:.0f} s in all)")
    return out


def check_reproduce(cfg: DictConfig) -> None:
    """Reject a bad scale, job count, launcher, tracking server, model, window, classical
    observer or training setting before any stage runs, not hours later in its stage."""
    from lbo.core.paths import CONF_DIR
    from lbo.scoring.grid import check_observers
    from lbo.scoring.outages import Outages
    from lbo.train import SLIP, check

    parts(cfg)
    integer(cfg.trials, "trials", 1)
    integer(cfg.jobs, "jobs", 1)
    Outages.from_cfg(cfg.get("outages"))  # the report's outages, in one line
    # the pose observers' searches: the side-slip observer's study is of the real run, not a
    # paper table
    searches = sorted(p.stem for p in (CONF_DIR / "hparams_search").glob("*.yaml")
                      if p.stem not in SLIP)
    for model in cfg.models:
        require(model in searches, "models", f"a list of models with a search space "
                f"({', '.join(searches)})", list(cfg.models))
    check_observers(list(cfg.classical), "classical")
    ready_launcher(cfg.launcher, "launcher")
    check_store(cfg.tracking_uri, "tracking_uri")
    jobs = train_jobs(cfg, Path(cfg.report_dir))
    if not jobs:
        raise LboError(f"study={cfg.study} trains nothing at scale {cfg.scale} (its models, "
                       "robust, literal or dynamic_study are empty); pick another study or "
                       "give it runs, e.g. dynamic_study=[dynamic]")
    # every training run's own checks (window, metric, train_overrides, ...), without the
    # tuned parameters, which do not exist yet
    for job in jobs:
        check(compose("train", [o for o in job.overrides
                                if not o.startswith(("+tuned=", "hydra.searchpath="))]))


def stage_data(cfg: DictConfig) -> tuple[Path, str]:
    """1: the scale's data sets, generated or reused; returns their folder."""
    from lbo.datagen import generate as datagen

    return Path(datagen(compose("datagen", [f"data={cfg.scale}", *cfg.overrides]))), "done"


def stage_tune(cfg: DictConfig, out: Path, models: list[str]) -> tuple[dict, str]:
    """2: one Optuna study per architecture of ``models`` at N=20 (resumed if it exists)."""
    from lbo.tune import quiet, tune

    quiet()
    results, reused = {}, True
    for model in models:
        c = compose("tune", respell([f"hparams_search={model}", f"experiment={cfg.scale}",
                                     f"tune.n_trials={cfg.trials}",
                                     f"tune.handoff={out / 'tuned' / f'{model}.yaml'}",
                                     f"tune.storage={cfg.optuna_storage}",
                                     *store_overrides(cfg.tracking_uri),
                                     f"output_dir={out / 'tune' / model}",
                                     *cfg.tune_overrides,
                                     *cfg.search_overrides[model],
                                     *cfg.overrides, *cfg.train_overrides]))
        results[model] = tune(c)
        reused &= not results[model]["new_trials"]
    return results, "reused" if reused else "done"


def expected(cfg: DictConfig, configs: dict[str, DictConfig]) -> Eta:
    """Measure a few steps of every run still to train (``configs``: each job's training
    config, by key); print the stage's expected time."""
    return plan(list(configs.items()), cfg.jobs if cfg.launcher == "joblib" else 1, cfg.scale)


def stage_train(cfg: DictConfig, out: Path, jobs: list[Job]) -> tuple[dict, str]:
    """3: train (or reuse) every observer, serially or through ``cfg.launcher``."""
    from lbo.train import train

    start_stage = time.perf_counter()

    study = {j.key: j.data for j in jobs if j.kind == DYNAMIC}

    def report_line(done: int, key: str, run: dict, how: str) -> None:
        on = f" on data={study[key]}" if key in study else ""
        # the job's key where it says more than the observer's name (literal-cnn-N60, robust)
        name = run["name"] if key == run["name"] else f"{key} ({run['name']})"
        print(f"    {done}/{len(jobs)} {name}{on}: {how}, NRMSE at alpha=1/3/6 "
              + "/".join(f"{run.get(f'test_nrmse_alpha_{a}', np.nan):.2f}" for a in (1, 3, 6))
              + f"  (stage {time.perf_counter() - start_stage:.0f} s)", flush=True)

    runs: dict[str, dict] = {}
    # composed once for the plan, the reuse and the training (a compose: 0.1-0.8 s)
    configs = {job.key: compose("train", list(job.overrides)) for job in jobs}
    eta = expected(cfg, configs)
    if cfg.launcher:
        # the runs that finished are reused here: a rerun queues no cluster job to learn that
        runs = finished_runs(configs)
        todo = [j for j in jobs if j.key not in runs]
        if todo:
            results = launch(cfg, [list(j.overrides) for j in todo], out / "runs",
                             [j.key for j in todo])
            runs.update((j.key, res) for j, res in zip(todo, results, strict=True))
        for done, job in enumerate(jobs, 1):
            res = runs[job.key]
            report_line(done, job.key, res, "reused" if res.get("reused") else "trained")
    for done, job in enumerate(jobs, 1):
        key = job.key
        if key in runs:
            continue
        start = time.perf_counter()
        runs[key] = train(configs[key])
        seconds = time.perf_counter() - start
        reused = bool(runs[key].get("reused"))
        left = eta.skipped(done - 1) if reused else eta.finished(done - 1, seconds)
        report_line(done, key, runs[key], ("reused" if reused else f"trained in {seconds:.0f} s")
                    + (f", ETA {duration(left)}" if done < len(jobs) else ""))
    return runs, "reused" if all(r.get("reused") for r in runs.values()) else "done"


def stage_classical(cfg: DictConfig, out: Path, folder: Path) -> tuple[pd.DataFrame, str]:
    """4: the classical observers on the test grid, reused while the data are the same."""
    from lbo.evaluate import evaluate

    csv = out / "classical" / "evaluation.csv"
    stamp = out / "classical" / "stamp.json"
    key = {"data": str(folder), "observers": list(cfg.classical)}
    if csv.is_file() and stamp.is_file() and json.loads(stamp.read_text()) == key:
        return pd.read_csv(csv), "reused"
    c = compose("evaluate", [f"data={cfg.scale}", f"observers=[{','.join(cfg.classical)}]",
                              f"output_dir={out / 'classical'}", *cfg.overrides])
    table = pd.read_csv(evaluate(c))
    write_text(stamp, json.dumps(key))
    return table, "done"


def stage_report(cfg: DictConfig, out: Path, folder: Path, tuned: dict, runs: dict,
                 classical_table: pd.DataFrame, record: dict, jobs: list[Job]
                 ) -> tuple[list[Path], str]:
    """5: the tables and figures, also logged to MLflow as a run of their own."""
    from lbo.scoring import report, studies

    # scored on test sets of their own (a dynamic job has its data set)
    mine = {j.key: cast(str, j.data) for j in jobs if j.kind == DYNAMIC}
    dynamic = {data: pd.concat([pd.read_csv(run_artifact(runs[k], "evaluation.csv",
                                                      cfg.tracking_uri))
                                for k, d in mine.items() if d == data],
                               ignore_index=True).drop_duplicates(["observer", "alpha"])
               for data in dict.fromkeys(mine.values())}
    run_ids = {f"{runs[k]['name']} on data={data}": runs[k]["run_id"] for k, data in mine.items()}
    # the states no sensor gives: the study's own observer per data set (its job's key)
    lateral = {j.data: _lateral(cfg, j, runs[j.key]) for j in jobs if j.key == j.data}
    literal = [j.key for j in jobs if j.kind == LITERAL]  # the paper's protocol, a section
    literal_table = pd.concat([_renamed(run_artifact(runs[k], "evaluation.csv", cfg.tracking_uri),
                                        runs[k]["name"], k) for k in literal],
                              ignore_index=True) if literal else None
    run_ids.update({k: runs[k]["run_id"] for k in literal})
    runs = {k: r for k, r in runs.items() if k not in mine and k not in literal}
    # the paper's and the robust observers' rows; none in a study of the car that slips alone
    learned = pd.concat([pd.read_csv(run_artifact(r, "evaluation.csv", cfg.tracking_uri))
                         for r in runs.values()] or [classical_table.iloc[:0]],
                        ignore_index=True)
    # each run's table also holds the EKF and oracle rows; the classical stage has them all
    table = pd.concat([learned[~learned["observer"].isin(classical.NAMES)], classical_table],
                      ignore_index=True)
    run_ids.update({r["name"]: r["run_id"] for r in runs.values()})
    for model, res in tuned.items():
        if res.get("parent_run_id"):
            run_ids[f"tune-{model}"] = res["parent_run_id"]
    best_cnn = report.best_window(table, "cnn")
    traj = _trajectory(folder, runs.get(best_cnn), cfg.trajectory_manoeuvre,
                       cfg.tracking_uri) if best_cnn else None
    sections: list[report.Section] = []
    if literal_table is not None:
        sections.append(report.Protocols(literal_table))
    robust = [runs[j.key]["name"] for j in jobs if j.kind == ROBUST]
    if robust:  # the robust observer first, the peers trained as it is beside it
        sections.append(studies.Robust(robust[0], tuple(robust[1:])))
        if cfg.get("outages") and cfg.outages.get("length_s"):  # and through GNSS outages
            sections.append(_outages(cfg, folder, [runs[j.key] for j in jobs
                                                   if j.kind == ROBUST]))
    sections += [studies.Dynamic(data, t, lateral=lateral.get(data))
                 for data, t in dynamic.items()]
    files = report.write(out, cfg.scale, table, run_ids, record, traj,
                         folder / "friction_circle.png", sections)
    _log_report(cfg, cfg.scale, out, files, folder.name)
    return files, "done"


def _outages(cfg: DictConfig, folder: Path, robust: list[dict]) -> Any:
    """The report's section on GNSS outages (``cfg.outages``) cut into the test grid: the
    robust observer and its peers (their runs ``robust``) beside the classical filters."""
    from lbo.scoring import studies
    from lbo.scoring.outages import Outages

    c = compose("evaluate", [f"data={cfg.scale}", *cfg.overrides])  # as the classical stage
    return studies.Outages.of(folder / "test.parquet", cast(Outages, Outages.from_cfg(
        cfg.outages)), c, [n for n in cfg.classical if n in classical.OBSERVERS],
        {r["name"]: _checkpoint(cfg, r) for r in robust})


def _lateral(cfg: DictConfig, job: Job, run: dict) -> pd.DataFrame | None:
    """The states no sensor gives on the car-that-slips study's test set: its observer's
    (``job``, trained as ``run``) where it carries a single-track body, and the classical
    estimators' (:func:`lbo.scoring.lateral.of_data`); None where the set has none."""
    from lbo.learn.builders import prepare_data
    from lbo.scoring import lateral

    c = compose("train", list(job.overrides))
    return lateral.of_data(Path(prepare_data(c)[0]) / "test.parquet", c,
                           {run["name"]: _checkpoint(cfg, run)})


def _checkpoint(cfg: DictConfig, run: dict) -> str:
    """The best checkpoint of a finished run, a local file."""
    return str(run_artifact(run, "checkpoints/best.ckpt", cfg.tracking_uri))


def finished_runs(configs: dict[str, DictConfig]) -> dict[str, dict[str, Any]]:
    """The jobs (their training ``configs`` by key, with ``resume=true``) whose run finished,
    by key: their metrics, as the training would return them (``reused``), found as it finds
    them (:func:`prior_runs <lbo.learn.resume.prior_runs>`: a shared store's run only where its
    folder shows it is this user's)."""
    from lbo.learn.identity import config_hash
    from lbo.learn.resume import finished_run

    found = {}
    for key, c in configs.items():
        if c.get("resume") and c.get("logger"):
            run = finished_run(c, config_hash(c))
            if run is not None:
                found[key] = run
    return found


def _renamed(csv: Path, name: str, key: str) -> pd.DataFrame:
    """A run's learned rows, its observer ``name`` renamed ``key`` (``literal-cnn-N60``)."""
    t = pd.read_csv(csv)
    return t[t["observer"] == name].assign(observer=key)


def _train_job(cfg: DictConfig) -> dict[str, Any]:
    """One training job of a launcher (a module-level function, so that it pickles)."""
    from lbo.core.runfolder import save_hydra_files
    from lbo.train import train

    save_hydra_files(cfg)  # Hydra writes none (hydra.output_subdir is null)
    return train(cfg)


def launch(cfg: DictConfig, job_overrides: list[list[str]], sweep_dir: Path,
           names: list[str]) -> list[dict[str, Any]]:
    """Train the jobs through the Hydra launcher ``cfg.launcher`` (joblib, submitit_local,
    submitit_slurm, ...); return each job's metrics, in order.

    The launcher gets what ``python -m lbo.train -m`` would give it: the training config with
    its Hydra node, and one override list per job. The jobs may differ in more than a grid's
    keys (the robust observer), which a command-line sweep cannot say. The overrides are
    read as lbo.train's command line reads them (``window=`` is ``model.window=``).
    """
    from hydra.core.hydra_config import HydraConfig
    from hydra.core.plugins import Plugins

    from lbo.core.cli import launcher_context

    master = compose("train", [f"hydra/launcher={cfg.launcher}", f"hydra.sweep.dir={sweep_dir}",
                               *([f"hydra.launcher.n_jobs={cfg.jobs}"]
                                 if cfg.launcher == "joblib" else []),
                               *cfg.launcher_overrides], return_hydra_config=True)
    own = HydraConfig.instance().cfg
    try:
        launcher = Plugins.instance().instantiate_launcher(
            hydra_context=launcher_context(master),
            task_function=_train_job, config=master)
        returns = launcher.launch([[*respell(o), f"hydra.sweep.subdir={n}"]
                                   for o, n in zip(job_overrides, names, strict=True)],
                                  initial_job_idx=0)
    finally:
        HydraConfig.instance().cfg = own  # the launcher set each job's in this process too
    return [r.return_value for r in returns]  # raises the first failed job's error


def _trajectory(folder: Path, run: dict[str, Any] | None, manoeuvre: str,
                tracking_uri: str) -> dict[str, np.ndarray] | None:
    """Fig. 6 arrays: one manoeuvre at alpha=3 with the best CNN and the EKF."""
    from lbo.models.checkpoint import read_checkpoint, trained_conditions
    from lbo.scoring.grid import classical, load_test, predict_grid

    if run is None:
        return None
    names = json.loads((folder / "manifest.json").read_text())["test_trajectories"]
    if manoeuvre not in names:
        manoeuvre = names[0]
    arr = load_test(folder / "test.parquet")
    pick = np.flatnonzero(np.isclose(arr.alpha, 3.0) & (arr.traj == names.index(manoeuvre)))
    if pick.size == 0:
        return None
    sub = arr.take(pick)
    ckpt = run_artifact(run, "checkpoints/best.ckpt", tracking_uri)
    net, hp = read_checkpoint(ckpt)
    vehicle, noise = trained_conditions(hp, ckpt)
    learned = predict_grid(net, sub, hp["window"])[0]
    ekf = classical("ekf", sub, vehicle, noise)[0]
    keep = sub.mask[0]
    return {"truth": sub.z[0][keep, :2], "meas": sub.m[0][keep, :2],
            "title": f"{manoeuvre.replace('_', ' ')}, alpha = 3",
            run["name"]: learned[keep, :2], "EKF": ekf[keep, :2]}


def _log_report(cfg: DictConfig, scale: str, out: Path, files: list[Path], data: str) -> None:
    """Log the report as an MLflow run of its own; a rerun updates the same run."""
    from lbo.core.paths import artifact_location
    from lbo.tracking.runs import ensure_experiment

    client, exp_id = ensure_experiment(cfg.tracking_uri, cfg.experiment_name,
                                       artifact_location(cfg.tracking_uri))
    found = client.search_runs([exp_id], f"tags.lbo_report = '{scale}' and tags.data = '{data}'")
    run_id = found[0].info.run_id if found else client.create_run(
        exp_id, run_name=f"report-{scale}", tags={"lbo_report": scale, "data": data}).info.run_id
    for f in files:
        client.log_artifact(run_id, str(f))
    client.set_terminated(run_id, "FINISHED")
    print(f"    report logged to MLflow run {run_id}")


def old_spellings(argv: list[str]) -> None:
    """Refuse ``<key>.<scale>=...`` (a setting of one scale, as lbo took it before the scale
    group) in one line that gives the new spelling. The scales and their settings are read
    from ``conf/scale/``, so that a new scale or setting needs no edit here."""
    from omegaconf import OmegaConf

    from lbo.core.paths import CONF_DIR

    files = {p.stem: p for p in (CONF_DIR / "scale").glob("*.yaml")}
    for arg in argv:
        key, _, value = arg.partition("=")
        head, _, rest = key.lstrip("+~").partition(".")
        scale, _, inner = rest.partition(".")
        if scale in files and head != "scale" and head in OmegaConf.load(files[scale]):
            new = f"{head}{'.' + inner if inner else ''}={value}"
            raise LboError(f"{arg}: each scale's settings are in conf/scale/{scale}.yaml now; "
                           f"write {new} scale={scale}")


main = entry("reproduce", reproduce, spellings=old_spellings)


if __name__ == "__main__":
    sys.exit(main())
