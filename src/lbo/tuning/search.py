"""How ``lbo.tune`` searches: the search space (training config keys and their Optuna
distributions), the sampler that proposes settings in it, and the pruner that stops trials."""

from __future__ import annotations

import json
from dataclasses import KW_ONLY, dataclass
from typing import Any, cast

import numpy as np
import optuna
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from optuna.trial import FrozenTrial

from lbo.core.checks import integer, number, require
from lbo.core.errors import LboError
from lbo.models import model_parameters
from lbo.models.slip_filter import SIDE_SLIP

DISTRIBUTIONS = {"float": {"low", "high", "log", "step"}, "int": {"low", "high", "log", "step"},
                 "categorical": {"choices"}}


@dataclass(frozen=True)
class Param:
    """One searched training setting: a dotted config key and its distribution.

    Categorical choices that Optuna cannot store (lists, such as LSTM widths) are offered to it
    as their JSON text and turned back into values by :meth:`decode`.
    """

    key: str
    kind: str
    _: KW_ONLY
    low: float | int | None = None
    high: float | int | None = None
    log: bool = False
    step: float | int | None = None
    choices: tuple[Any, ...] = ()

    @property
    def labels(self) -> tuple[Any, ...]:
        return tuple(json.dumps(c) if isinstance(c, (list, dict)) else c for c in self.choices)

    def suggest(self, trial: optuna.Trial) -> Any:
        # a float's or an int's low and high are numbers (search_space checks them), an
        # int's step an int
        if self.kind == "float":
            return trial.suggest_float(self.key, cast(float, self.low), cast(float, self.high),
                                       log=self.log, step=self.step)
        if self.kind == "int":
            return trial.suggest_int(self.key, cast(int, self.low), cast(int, self.high),
                                     log=self.log, step=cast(int, self.step or 1))
        return self.decode(trial.suggest_categorical(self.key, self.labels))

    def decode(self, raw: Any) -> Any:
        """A value as Optuna stores it -> the config value."""
        if self.kind == "categorical" and raw in self.labels:
            return self.choices[self.labels.index(raw)]
        return raw

    def contains(self, raw: Any) -> bool:
        """Whether a value as Optuna stores it lies in this distribution (its range and step,
        or its choices): a trial of an older, wider space may not."""
        if self.kind == "categorical":
            return raw in self.labels
        if isinstance(raw, bool) or not isinstance(raw, (int, float)):
            return False
        low, high = cast(float, self.low), cast(float, self.high)  # a float's or an int's
        span = (high - low) or 1
        if not low - 1e-9 * span <= raw <= high + 1e-9 * span:
            return False
        step = self.step or (1 if self.kind == "int" else None)
        if step is None:
            return True
        k = (raw - low) / step
        return abs(k - round(k)) < 1e-6

    @property
    def bounds(self) -> str:
        """The range or the choices, as a message names them: ``[0.0001, 0.003]``."""
        if self.kind == "categorical":
            return _choices_text(self.labels)
        return f"[{self.low:g}, {self.high:g}]"

    def distribution(self) -> optuna.distributions.BaseDistribution:
        """This parameter as the Optuna distribution its trials are stored with."""
        if self.kind == "float":  # bounds and steps as in suggest
            return optuna.distributions.FloatDistribution(
                cast(float, self.low), cast(float, self.high), log=self.log, step=self.step)
        if self.kind == "int":
            return optuna.distributions.IntDistribution(
                cast(int, self.low), cast(int, self.high), log=self.log,
                step=cast(int, self.step or 1))
        return optuna.distributions.CategoricalDistribution(self.labels)


KINDS = {"FloatDistribution": "float", "IntDistribution": "int",
         "CategoricalDistribution": "categorical"}


def _a(word: str) -> str:
    return f"an {word}" if word[0] in "aeiou" else f"a {word}"


def _choices_text(labels: Any) -> str:
    """Choices as a message shows them: ``[64, 128]``, ``[[4, 8], [8, 16]]`` (list choices are
    stored as their JSON text)."""
    def one(c: Any) -> str:
        if isinstance(c, str) and c[:1] in "[{":
            return c
        return json.dumps(c)

    return "[" + ", ".join(one(c) for c in labels) + "]"


def _categorical(d: optuna.distributions.BaseDistribution
                 ) -> optuna.distributions.CategoricalDistribution:
    """A distribution of the kind ``categorical`` (:data:`KINDS`, by its type's name)."""
    return cast(optuna.distributions.CategoricalDistribution, d)


def _ranged(d: optuna.distributions.BaseDistribution
            ) -> optuna.distributions.FloatDistribution | optuna.distributions.IntDistribution:
    """A distribution of the kind ``float`` or ``int`` (:data:`KINDS`)."""
    return cast(optuna.distributions.FloatDistribution | optuna.distributions.IntDistribution, d)


def check_resumed(trials: list[optuna.trial.FrozenTrial], space: list[Param],
                  study: str) -> None:
    """Refuse (one line) a search space that the stored trials of a resumed study cannot share.

    Optuna keeps one distribution per parameter and study: the same kind, the same log scale
    and, for a categorical parameter, the same choices (ranges may change). A trial with a
    changed one would fail inside Optuna, one more failed trial per run.
    ``study`` names the study and its storage in the message.
    """
    stored: dict[str, optuna.distributions.BaseDistribution] = {}
    for trial in trials:
        for key, dist in trial.distributions.items():
            stored.setdefault(key, dist)
    for p in space:
        old = stored.get(p.key)
        if old is None:
            continue
        new = p.distribution()
        kind = KINDS.get(type(old).__name__, type(old).__name__)
        if kind != p.kind:
            was, now, what = f"{_a(kind)} distribution", f"{_a(p.kind)} one", "its type"
        # the same kind: both categorical, or both of a range (a float's or an int's)
        elif p.kind == "categorical" and tuple(_categorical(old).choices) != tuple(
                _categorical(new).choices):
            was = f"choices {_choices_text(_categorical(old).choices)}"
            now, what = _choices_text(_categorical(new).choices), "its choices"
        elif p.kind != "categorical" and bool(_ranged(old).log) != p.log:
            was, now = f"log: {str(_ranged(old).log).lower()}", f"log: {str(p.log).lower()}"
            what = "its log scale"
        else:
            continue
        raise LboError(f"tune.search_space.{p.key}: study {study} was run with {was}, the "
                       f"search space now has {now}; restore {what}, or start a new study "
                       f"with another tune.study_name")


def search_space(cfg: DictConfig) -> list[Param]:
    """``tune.search_space`` as a list of :class:`Param`, checked against the training config
    and the model's parameters; raise :class:`LboError` (one line) for anything wrong."""
    node = cfg.tune.get("search_space")
    raw = OmegaConf.to_container(node, resolve=True) if node is not None else {}
    if not isinstance(raw, dict):
        raise LboError(f"tune.search_space must be a mapping of config keys to distributions, "
                       f"got {raw!r}")
    params: list[Param] = []

    def walk(tree: dict[Any, Any], prefix: str) -> None:
        for name, value in tree.items():
            key = f"{prefix}{name}"
            if isinstance(value, dict) and "type" not in value:
                walk(value, f"{key}.")
            else:
                params.append(_param(cfg, key, value))

    walk(raw, "")
    if not params:
        from lbo.core.paths import CONF_DIR

        searches = sorted(p.stem for p in (CONF_DIR / "hparams_search").glob("*.yaml"))
        raise LboError(f"tune.search_space is empty: choose a search with hparams_search="
                       f"{'|'.join(searches)}, or declare one under tune.search_space")
    return params


def _param(cfg: DictConfig, key: str, spec: Any) -> Param:
    field = f"tune.search_space.{key}"
    if not isinstance(spec, dict) or spec.get("type") not in DISTRIBUTIONS:
        raise LboError(f"{field} must be {{type: float|int|categorical, ...}}, got {spec!r}")
    kind = spec["type"]
    extra = set(spec) - DISTRIBUTIONS[kind] - {"type"}
    if extra:
        raise LboError(f"{field}: unknown field {sorted(extra)[0]!r} for a {kind} distribution; "
                       f"expected {', '.join(sorted(DISTRIBUTIONS[kind]))}")
    _check_key(cfg, key, field)
    if kind == "categorical":
        choices = spec.get("choices")
        require(isinstance(choices, list) and len(choices) > 0, f"{field}.choices",
                "a non-empty list", choices)
        return Param(key, kind, choices=tuple(cast(list, choices)))  # a list: required above
    # raw config values, checked below
    low: Any = spec.get("low")
    high: Any = spec.get("high")
    log, step = spec.get("log", False), spec.get("step")
    bound = integer if kind == "int" else number
    for name, value in (("low", low), ("high", high)):
        bound(value, f"{field}.{name}")
    require(low <= high, f"{field}.high", f">= low ({low})", high)
    require(isinstance(log, bool), f"{field}.log", "true or false", log)
    require(not log or low > 0, f"{field}.low", "> 0 on a log scale", low)
    if step is not None:
        form = "a positive number, and not with log: true"
        if kind == "int":
            integer(step, f"{field}.step", 1, form=form)
        else:
            number(step, f"{field}.step", low=0.0, low_open=True, form=form)
        require(not log, f"{field}.step", form, step)
    return Param(key, kind, low=low, high=high, log=log, step=step)


_MISSING = object()


def _check_key(cfg: DictConfig, key: str, field: str) -> None:
    """The key must name a setting that training reads: a parameter the model accepts, or a
    value already in the training config."""
    if key.startswith("model."):
        name = key[len("model."):]
        accepted = (SIDE_SLIP[cfg.model.name] if cfg.model.name in SIDE_SLIP  # not a pose
                    else model_parameters(cfg.model.name))              # window's net
        if name not in accepted:
            raise LboError(f"{field}: {name!r} is not a parameter of model {cfg.model.name!r}; "
                           f"accepted: {', '.join(accepted)}")
        return
    if key.split(".")[0] in ("tune", "hydra", "window", "seed", "data", "data_dir", "output_dir"):
        raise LboError(f"{field}: {key.split('.')[0]!r} is not a hyperparameter; the study "
                       f"searches training settings at a fixed window, seed and data set")
    value = OmegaConf.select(cfg, key, default=_MISSING, throw_on_missing=False)
    if value is _MISSING:
        raise LboError(f"{field}: no key {key!r} in the training config")
    if OmegaConf.is_config(value):
        raise LboError(f"{field}: {key!r} is a group of settings; search its values one by one")


def short_value(value: Any) -> str:
    """A setting as the study's messages show it: floats to 4 digits, lists as JSON."""
    if isinstance(value, float):
        return f"{value:.4g}"
    return json.dumps(value, separators=(",", ":")) if isinstance(value, list) else str(value)


class TrialSeededTPESampler(optuna.samplers.BaseSampler):
    """TPE whose random draws for trial n depend only on (seed, n).

    A plain seeded sampler restarts its random stream in every process: a resumed study would
    repeat its first proposals, and workers sharing a study would propose the same ones. Seeding
    per trial keeps a study repeatable and lets any number of processes share it. Each trial
    gets a fresh :class:`optuna.samplers.TPESampler` seeded with (seed, n), through Optuna's
    public sampler interface: TPE keeps no state between trials but its random stream, and
    reads the history from the study.
    """

    def __init__(self, *, seed: int, **kwargs: Any) -> None:
        self.seed, self.tpe_kwargs = seed, kwargs
        self.tpe = self.for_trial(0)

    def for_trial(self, number: int) -> optuna.samplers.TPESampler:
        seed = int(np.random.SeedSequence([self.seed, number]).generate_state(1)[0])
        return optuna.samplers.TPESampler(seed=seed, **self.tpe_kwargs)

    def reseed_rng(self) -> None:  # the per-trial seeds already differ
        return None

    def before_trial(self, study: optuna.Study, trial: FrozenTrial) -> None:
        self.tpe = self.for_trial(trial.number)
        self.tpe.before_trial(study, trial)

    def infer_relative_search_space(self, study, trial):
        return self.tpe.infer_relative_search_space(study, trial)

    def sample_relative(self, study, trial, search_space):
        return self.tpe.sample_relative(study, trial, search_space)

    def sample_independent(self, study, trial, param_name, param_distribution):
        return self.tpe.sample_independent(study, trial, param_name, param_distribution)

    def after_trial(self, study, trial, state, values) -> None:
        self.tpe.after_trial(study, trial, state, values)


def make_pruner(node: DictConfig) -> optuna.pruners.BasePruner:
    """``tune.pruner`` (a ``_target_`` config, MedianPruner by default) as a pruner."""
    try:
        pruner = instantiate(node)
    except Exception as e:
        cause = e.__cause__ or e
        reason = " ".join(str(cause).split())[:300]
        raise LboError(f"tune.pruner: cannot build {node.get('_target_')!r} "
                       f"({type(cause).__name__}: {reason})") from e
    if not isinstance(pruner, optuna.pruners.BasePruner):
        raise LboError(f"tune.pruner must build an optuna pruner, got {type(pruner).__name__}")
    return pruner
