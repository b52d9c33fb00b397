"""The training runs of ``python -m lbo.reproduce``'s study, as typed jobs: which observers
its train stage trains at a scale, with which overrides, and which part of the report each
belongs to. ``study`` picks the parts: the paper's study, the car that slips, or both."""

from __future__ import annotations

import dataclasses
import re
from dataclasses import KW_ONLY, dataclass
from pathlib import Path
from typing import cast

from omegaconf import DictConfig

from lbo.core.checks import require
from lbo.core.cli import respell
from lbo.core.paths import store_overrides

STUDIES = ("paper", "dynamic", "all")
"""``study=``: the paper's study (its eight observers tuned and trained, the robust observer
and the learned peers beside it, the paper's protocol), the car that slips, or both."""

PAPER, ROBUST, LITERAL, DYNAMIC = "paper", "robust", "literal", "dynamic"
"""The kinds of training job: the paper's eight observers, the robust observer, the paper's
protocol beside ours, and the car-that-slips study (each its own part of the report)."""


@dataclass(frozen=True)
class Job:
    """One training run of the study.

    key : its name in the study and its run folder (``cnn-N20``, ``robust``, ``robust-kalmannet``,
        ``literal-cnn-N60``, ``dynamic``, ``dynamic-cnn``).
    kind : :data:`PAPER`, :data:`ROBUST`, :data:`LITERAL` or :data:`DYNAMIC`.
    overrides : ``lbo.train``'s overrides.
    data : the data set a :data:`DYNAMIC` job trains and is scored on (None for the others).
    """

    key: str
    kind: str
    overrides: tuple[str, ...]
    _: KW_ONLY
    data: str | None = None


def model_window(name: str, field: str) -> tuple[str, int]:
    """``cnn-N60`` -> ("cnn", 60); anything else a one-line error naming ``field``."""
    found = re.fullmatch(r"([a-z][a-z0-9_]*)-N([1-9][0-9]*)", str(name))
    require(found is not None, field, "a list of <model>-N<window> (e.g. cnn-N60)", name)
    found = cast(re.Match[str], found)  # required just above
    return found.group(1), int(found.group(2))


def run_name(study: str) -> str:
    """The MLflow run name of a job of ``study``: ``literal-cnn-N20`` beside the paper
    protocol's ``cnn-N20`` (the logger config's name alone would give both the same; the
    name is not part of a run's config hash, so finished runs are still reused)."""
    return f"logger.run_name={study}-${{model.name}}-N${{model.window}}"


def parts(cfg: DictConfig) -> tuple[bool, bool]:
    """Whether ``cfg.study`` holds the paper's study (its eight observers, their tuning, the
    robust observer and its peers, the paper's protocol) and the car-that-slips study; one
    line for anything but :data:`STUDIES`."""
    study = cfg.get("study", "paper")
    require(study in STUDIES, "study", "paper, dynamic or all", study)
    return study in ("paper", "all"), study in ("dynamic", "all")


def train_jobs(cfg: DictConfig, out: Path) -> list[Job]:
    """Every run the train stage trains (or reuses) for ``cfg.study``, in order."""
    paper, dynamic = parts(cfg)
    jobs = [Job(f"{model}-N{window}", PAPER,
                (f"experiment={cfg.scale}", *cfg.paper_overrides, f"model={model}",
                 f"model.window={window}", f"+tuned={model}",
                 f"hydra.searchpath=[file://{out}]"))
            for model in (cfg.models if paper else []) for window in cfg.windows]
    if cfg.robust and paper:
        jobs.append(Job("robust", ROBUST, ("experiment=robust", f"data={cfg.scale}",
                                           *cfg.robust_overrides,
                                           run_name("robust"))))
        # the learned peers of the literature, trained as the robust observer is
        for model in cfg.peers:
            jobs.append(Job(f"robust-{model}", ROBUST, (
                "experiment=robust", f"model={model}", f"data={cfg.scale}",
                *cfg.robust_overrides, run_name("robust"))))
    for name in cfg.literal if paper else []:
        model, window = model_window(name, "literal")
        jobs.append(Job(f"literal-{model}-N{window}", LITERAL,
                        (*cfg.literal_overrides, f"model={model}",
                         f"model.window={window}", run_name("literal"))))
    # the car that slips: on each data set the observer that learns the model error (keyed
    # by the data set), and on the first one the black-box peers (<data>-cnn, <data>-lstm)
    # and the learned peers (<data>-kalmannet, <data>-split_kalmannet)
    for i, data in enumerate(cfg.dynamic_study if dynamic else []):
        jobs.append(Job(data, DYNAMIC, ("experiment=dynamic", f"data={data}",
                                        *cfg.dynamic_overrides, run_name(data)),
                        data=data))
        for model in (cfg.dynamic_blackbox if i == 0 else []):
            jobs.append(Job(f"{data}-{model}", DYNAMIC,
                            ("experiment=dynamic_blackbox", f"model={model}", f"data={data}",
                             *cfg.dynamic_overrides, run_name(data)), data=data))
        # the learned peers around the single-track body, which has no drift states
        for model in (cfg.dynamic_peers if i == 0 else []):
            jobs.append(Job(f"{data}-{model}", DYNAMIC,
                            ("experiment=dynamic", f"model={model}", "~model.drift",
                             f"data={data}", *cfg.dynamic_overrides,
                             run_name(data)), data=data))
    # each run's progress bars hidden: the stage says each run's result as it ends; each run
    # logs to the store the report reads (the command's tracking_uri)
    return [dataclasses.replace(j, overrides=tuple(respell(
        [*j.overrides, "callbacks.progress_bar.refresh_rate=0", "resume=true",
         *store_overrides(cfg.tracking_uri),
         f"output_dir={out / 'runs' / j.key}", *cfg.overrides, *cfg.train_overrides])))
        for j in jobs]
