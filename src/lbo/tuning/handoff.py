"""A study's outcome as a config: the best trial inside the search space written as a
``# @package _global_`` file (``tune.handoff``), and the training line that composes it."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import cast

import optuna
from omegaconf import DictConfig, OmegaConf
from optuna.trial import FrozenTrial, TrialState

from lbo.core.atomic import write_text
from lbo.core.paths import CONF_DIR
from lbo.core.redact import scrub
from lbo.tuning.search import Param, short_value


def best_trials(study: optuna.Study,
                space: list[Param]) -> tuple[FrozenTrial | None, FrozenTrial | None]:
    """``(best, better)``: the best completed trial whose settings lie in the search space, and
    a better completed trial outside it (a range narrowed since it ran), or None."""
    done = sorted(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)),
                  key=lambda tr: (tr.value, tr.number))
    inside = [tr for tr in done if not outside_space(tr, space)]
    best = inside[0] if inside else None
    # a completed trial has its value
    better = (done[0] if done and (best is None or cast(float, done[0].value)
                                   < cast(float, best.value)) else None)
    return best, better


def outside_space(trial: FrozenTrial, space: list[Param]) -> str:
    """The trial's settings that the search space no longer holds, e.g.
    ``optimizer.lr=0.005 not in [0.0001, 0.003]``; empty when it holds them all."""
    return ", ".join(f"{p.key}={short_value(p.decode(trial.params[p.key]))} not in {p.bounds}"
                     for p in space if p.key in trial.params
                     and not p.contains(trial.params[p.key]))


def outside_note(better: FrozenTrial, best: FrozenTrial, space: list[Param]) -> str:
    return (f"note: trial {better.number} (val_loss {better.value:.6g}) is better than trial "
            f"{best.number} (val_loss {best.value:.6g}) but lies outside the current search "
            f"space ({outside_space(better, space)}); the hand-off takes trial {best.number}, the "
            f"best inside it")


def write_handoff(cfg: DictConfig, study: optuna.Study, space: list[Param],
                  storage: str, best: FrozenTrial | None = None) -> Path:
    """Write the best trial's settings (``best``, or the study's best) as a
    ``# @package _global_`` config (atomically)."""
    best = best if best is not None else study.best_trial
    values = OmegaConf.create({})
    for p in space:
        if p.key in best.params:
            OmegaConf.update(values, p.key, p.decode(best.params[p.key]), merge=True)
    path = Path(cfg.tune.handoff)
    header = (
        "# @package _global_\n"
        f"# Written by `python -m lbo.tune`: the best of study {study.study_name!r} in "
        f"{scrub(storage)}\n"
        f"# (model {cfg.model.name}, window {cfg.model.window}, data {cfg.data.name}; trial "
        f"{best.number}, val_loss {best.value:.6g}).\n"
        f"# Use: {train_command(cfg.model.name, path, hydra_searchpath(), cfg.model.features)}\n")
    return write_text(path, header + OmegaConf.to_yaml(values))


def train_command(model: str, handoff: Path, searchpath: Sequence[str] = (),
                  features: str = "relative") -> str:
    """The training line that composes ``handoff``: ``+<folder>=<name>``, with a search path
    when the folder is not under conf/. ``searchpath``: the study's own search path (e.g. a
    plug-in's configs), kept in front; ``features``: the study's, said where it is not the
    training default (a search such as ``hparams_search=kalmannet`` sets ``frame``)."""
    handoff = Path(handoff).resolve()
    command = (f"python -m lbo.train -m model={model} +{handoff.parent.name}={handoff.stem} "
               f"window=20,40,60,80")
    if features != "relative":
        command += f" features={features}"
    paths = list(searchpath)
    if handoff.parent.parent != CONF_DIR.resolve():
        paths.append(f"file://{handoff.parent.parent}")
    if paths:
        command += f" 'hydra.searchpath=[{','.join(paths)}]'"
    return command


def hydra_searchpath() -> list[str]:
    """The running command's ``hydra.searchpath`` (empty outside a Hydra run)."""
    from hydra.core.hydra_config import HydraConfig

    return list(HydraConfig.get().searchpath) if HydraConfig.initialized() else []
