"""Every option of every config group composes, with every experiment, and passes the checks
its command runs before any data is made or any run opens, or is refused in one line naming
the field, exactly as listed here with the reason.

The options are found by listing ``conf/`` when the tests are collected, so a new option file
(or experiment, or data set) is covered without touching this module. Training is composed as
``experiment=E G=O`` for each experiment E (and none) and each option O of each other group G
of ``train.yaml``: not the full cross product of the groups, which would be thousands of runs
(where O is the option E picks anyway, that config is E's own, composed once). Each composed
config must keep every setting its option files make, the later winning as Hydra merges them.
The other commands (``datagen``, ``evaluate``, ``simulate``, ``observe``, ``export``) are
composed with each option of their own groups, ``tune`` with each search and experiment,
``reproduce`` at each scale. Nothing trains and no data is generated: each case takes a
fraction of a second.
"""

from __future__ import annotations

import functools
import re
from pathlib import Path
from typing import Any, NamedTuple

import pytest
from hydra import initialize_config_dir
from omegaconf import OmegaConf

from helpers import compose_cfg
from lbo.core.errors import LboError
from lbo.core.paths import CONF_DIR

# --- what conf/ holds, read when the tests are collected ---------------------------------------


def options(group: str) -> list[str]:
    """The options of a config group: the stems of ``conf/<group>/*.yaml``."""
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


@functools.cache
def read(path: Path) -> dict[str, Any]:
    """A config file's contents, unresolved; read once per run (conf/ does not change while
    the tests run, and a few hundred cases read the same files)."""
    return OmegaConf.to_container(OmegaConf.load(path), resolve=False)


def defaults(path: Path) -> list[Any]:
    """The defaults list of a config file, as written."""
    return list(read(path).get("defaults", []))


def default_choices(primary: str) -> dict[str, str | None]:
    """group -> the option a primary config chooses (None for ``experiment: null``), for the
    groups that are folders of ``conf/``; ``override`` entries are left out."""
    return {group: option for entry in defaults(CONF_DIR / f"{primary}.yaml")
            if isinstance(entry, dict) for group, option in entry.items()
            if not group.startswith("override ") and (CONF_DIR / group).is_dir()}


def groups(primary: str) -> list[str]:
    """The config groups a primary config chooses from (``hydra`` included)."""
    return list(default_choices(primary))


def overridden(config: Path) -> dict[str, str]:
    """group -> option of the ``override /<group>: <option>`` entries of a config file (an
    experiment's data, model and training noise), those of the option it starts from
    (``defaults: [dynamic]``) first."""
    out: dict[str, str] = {}
    for entry in defaults(config):
        if isinstance(entry, str) and entry != "_self_":  # the option it starts from
            out.update(overridden(config.parent / f"{entry}.yaml"))
        elif isinstance(entry, dict):
            out.update({group[len("override /"):]: option for group, option in entry.items()
                        if group.startswith("override /") and "@" not in group})
    return out


def data_picks(option: str) -> dict[str, str]:
    """The car and sensors a data option picks (``override /car@_global_.car: <car>``, the
    same for ``sensors``), through the options it starts from; a group it leaves out keeps
    train.yaml's."""
    picks: dict[str, str] = {}
    for entry in defaults(CONF_DIR / "data" / f"{option}.yaml"):
        if isinstance(entry, str) and entry != "_self_":
            picks.update(data_picks(entry))
        elif isinstance(entry, dict):
            for key, value in entry.items():
                for group in ("car", "sensors"):
                    if key.startswith(f"override /{group}@"):
                        picks[group] = value
    return picks


PRIMARIES = sorted(p.stem for p in CONF_DIR.glob("*.yaml"))
TRAIN_GROUPS = [g for g in groups("train") if g != "experiment"]
EXPERIMENTS = [None, *options("experiment")]
SEARCHES = [None, *options("hparams_search")]
SLIP_MODELS = ("slip_gru", "slip_filter")
"""The side-slip observers, which learn on the side-slip run and its kind alone."""
POSE_SEARCHES = [s for s in SEARCHES[1:] if s not in SLIP_MODELS]
"""The studies of the pose observers, which make reproduce runs (the side-slip observers' are
the real side-slip run's, with a data set of its own)."""
COMMANDS = ["datagen", "evaluate", "simulate", "observe", "export"]
"""The primary configs composed with each option of their own groups here (train, tune and
reproduce have tests of their own below)."""
SCALES = options("scale")
LOCAL_GROUPS = {"tuned": "lbo.tune's handoff (git-ignored), composed with +tuned=<name>"}


def chosen(experiment: str | None, group: str | None = None, option: str | None = None,
           search: str | None = None) -> dict[str, str | None]:
    """The option of each training group that ``experiment=E [G=O] [hparams_search=S]``
    ends up with: train.yaml's, then the experiment's overrides, then the search's, then the
    command line's (Hydra's order), and the car and sensors the data set picks unless G is
    that group."""
    out = default_choices("train")
    if experiment is not None:
        out.update(overridden(CONF_DIR / "experiment" / f"{experiment}.yaml"))
    if search is not None:
        out.update(overridden(CONF_DIR / "hparams_search" / f"{search}.yaml"))
    if group is not None:
        out[group] = option
    picks = data_picks(str(out["data"]))
    for g in ("car", "sensors"):
        if group != g:  # the command line's choice wins over the data set's
            out[g] = picks.get(g) or out[g]
    return out


def name(experiment: str | None) -> str:
    return experiment or "no-experiment"


def exp(experiment: str | None) -> list[str]:
    return [] if experiment is None else [f"experiment={experiment}"]


# --- the settings a composed config must keep ---------------------------------------------------


def flat(node: Any, prefix: str = "") -> dict[str, Any]:
    """``a.b.c -> value`` of every leaf of a nested container (lists are leaves)."""
    if not isinstance(node, dict):
        return {prefix[:-1]: node}
    out: dict[str, Any] = {}
    for key, value in node.items():
        out.update(flat(value, f"{prefix}{key}."))
    return out


def own_settings(group: str, option: str) -> dict[str, Any]:
    """The leaves an option file sets itself (its defaults list left out), keyed by where they
    land in the composed config: under the group, or at the root for ``@package _global_``."""
    path = CONF_DIR / group / f"{option}.yaml"
    out: dict[str, Any] = {}
    for entry in defaults(path):  # an option it starts from (`defaults: [paper]`): first
        if isinstance(entry, str) and entry != "_self_":
            out.update(own_settings(group, entry))
    raw = {k: v for k, v in read(path).items() if k != "defaults"}
    is_global = path.read_text().lstrip().startswith("# @package _global_")
    return {**out, **flat(raw, "" if is_global else f"{group}.")}


def assert_kept(cfg, *sources: tuple[str, str | None]) -> None:
    """Every leaf each ``(group, option)`` file sets is in ``cfg`` with its value, a later
    source winning where two set the same key (as Hydra merges them); ``hydra`` settings are
    not part of a composed job config, and are skipped."""
    expected: dict[str, Any] = {}
    for group, option in sources:
        if option is not None and group != "hydra":
            expected.update(own_settings(group, option))
    actual = flat(OmegaConf.to_container(cfg, resolve=False))
    lost = {k: (v, actual.get(k, "<missing>")) for k, v in expected.items()
            if actual.get(k, "<missing>") != v}
    assert not lost, f"settings lost in composition (key: (set, composed)): {lost}"


# --- the refusals expected, each with its reason -------------------------------------------------


class Refusal(NamedTuple):
    pattern: str
    """A regex the one-line message matches, from its start: it names the field."""
    reason: str
    """Why the combination is refused, legitimately."""


NEEDS_LOGS = Refusal(r"data\.train must be a list of log files",
                     "data=logs trains on the user's own logs (data.train=[...], ...), and "
                     "these cases name none")
NEEDS_TEST_LOGS = Refusal(r"data\.test must be a list of log files",
                          "lbo.evaluate data=logs scores the user's test logs "
                          "(data.test=[...]), and these cases name none")
FILTERNET_ONLY = Refusal(r"model\.(body|body_lr|residual|drift): not a parameter of model",
                         "experiment=dynamic, dynamic_carried and logs set the filternet's learned "
                         "body, residual and drift; their black-box peers are "
                         "experiment=dynamic_blackbox model=cnn|lstm")
NO_CUDA = Refusal(r"trainer=gpu needs CUDA",
                  "trainer=gpu where torch sees no CUDA device (passes where it does)")
NO_SEARCH = Refusal(r"tune\.search_space is empty",
                    "a study needs a search space: hparams_search=cnn|lstm")
NOT_SIMULATED = Refusal(r".*\bdata\b",
                        "lbo.simulate drives the simulated test manoeuvres of a data set's "
                        "settings; a user's logs (data=logs) have none")

NEEDS_FIX_RATES = Refusal(r"fix_rates must be the rates \(Hz\) of the receiver's fixes",
                          "a net that reads a receiver (receiver=...) is trained on receivers "
                          "drawn at the fix rates of its windows, which only experiment=robust, "
                          "logs and receiver set")
RECEIVER_MODEL = Refusal(r"receiver: model '(split_)?kalmannet' does not read a receiver's "
                         r"windows", "KalmanNet and Split-KalmanNet read a paper window (the "
                         "CNN, the LSTM and the window filter read a receiver's)")
RECEIVER_DRIFT = Refusal(r"model.drift: expected false for a window filter that reads a "
                         r"receiver", "experiment=logs sets model.drift=true; the window "
                         "filter's drift states read a paper window only")

GYRO_NEEDS_LOGS = Refusal(r"data: model=gyro_ekf learns from a vehicle's logs",
                          "the gyro EKF's noise is learned on logs with a gyro and one antenna")

SLIP_DATA = ("sideslip", "sideslip_sim")
"""The side-slip observer's data sets, which only it reads."""
SLIP_NEEDS_RUN = Refusal(r"data: model=slip_(gru|filter) learns on the side-slip run",
                         "the side-slip observer learns on the real run (data=sideslip) or on "
                         "simulated runs of its kind (data=sideslip_sim)")
SIDESLIP_SLIP_ONLY = Refusal(r"data: data=sideslip(_sim)? is (the real side-slip run|simulated "
                             r"runs of the side-slip run's kind), which the side-slip "
                             r"observers alone", "the real side-slip run is read by the "
                             "side-slip observers alone: no pose "
                             "observer, data set or test grid is made of it")
SLIP_RECEIVER = Refusal(r"receiver: expected None with model=slip_(gru|filter)",
                        "the side-slip observer reads a car's lateral sensors, not a receiver")
SLIP_FIX_RATES = Refusal(r"fix_rates: expected None with model=slip_(gru|filter)",
                         "the side-slip observer reads no position fixes")
SLIP_SCHEDULE = Refusal(r"lr_schedule: expected constant with model=slip_(gru|filter)",
                        "the side-slip observer trains at a constant rate; these experiments "
                        "set the pose observers' cosine schedule")

FILTERNET_EXPERIMENTS = {"dynamic", "dynamic_carried", "logs"}
"""Experiments that set model keys only the filternet takes (refused for other models)."""
FIX_RATE_EXPERIMENTS = {"robust", "logs", "receiver"}
"""Experiments that set ``fix_rates`` (a receiver's training windows need them)."""
COSINE_EXPERIMENTS = {"dynamic", "dynamic_blackbox", "logs", "quick", "quick_literal",
                      "receiver", "robust"}
"""Experiments that set ``lr_schedule: cosine``."""


def cuda() -> bool:
    import torch

    return torch.cuda.is_available()


def train_refusal(experiment: str | None, choice: dict[str, str | None],
                  search: str | None = None) -> Refusal | None:
    """The refusal ``lbo.train.check`` gives, in the order it checks; None: it passes.
    ``search``: the hparams_search composed last, whose settings win."""
    if choice["model"] == "gyro_ekf":  # lbo.learn.noise_run.check: no net, a vehicle's logs
        return (GYRO_NEEDS_LOGS if choice["data"] not in ("logs", "hill")
                else NEEDS_LOGS if choice["data"] == "logs" else None)
    if choice["model"] in SLIP_MODELS:  # lbo.learn.slip_run.check: the real run, its own net
        if choice["data"] not in SLIP_DATA:
            return SLIP_NEEDS_RUN
        if experiment in FILTERNET_EXPERIMENTS:  # their model keys come first
            return FILTERNET_ONLY
        if choice.get("receiver") is not None:
            return SLIP_RECEIVER
        if experiment in FIX_RATE_EXPERIMENTS:
            return SLIP_FIX_RATES
        if experiment in COSINE_EXPERIMENTS:
            return SLIP_SCHEDULE
        return NO_CUDA if choice["trainer"] == "gpu" and not cuda() else None
    if choice["data"] in SLIP_DATA:
        return SIDESLIP_SLIP_ONLY
    if choice.get("receiver") is not None:
        if experiment not in FIX_RATE_EXPERIMENTS:
            return NEEDS_FIX_RATES
        if choice["model"] in ("kalmannet", "split_kalmannet"):
            return RECEIVER_MODEL
        if choice["model"] == "filternet" and experiment == "logs":
            return RECEIVER_DRIFT
    if experiment in FILTERNET_EXPERIMENTS and choice["model"] != "filternet":
        return FILTERNET_ONLY
    if choice["data"] == "logs":
        return NEEDS_LOGS
    if choice["trainer"] == "gpu" and not cuda():
        return NO_CUDA
    return None


def expect(checks, refusal: Refusal | None) -> None:
    """Run ``checks()``: it passes, or raises the one-line LboError ``refusal`` names."""
    if refusal is None:
        checks()
        return
    with pytest.raises(LboError) as info:
        checks()
    message = str(info.value)
    assert "\n" not in message, f"not one line: {message!r}"
    assert re.match(refusal.pattern, message), (
        f"{message!r} is not the refusal listed, /{refusal.pattern}/ ({refusal.reason})")


# --- the checks each command runs before any data or run ----------------------------------------


def train_checks(cfg) -> None:
    """What ``lbo.train`` checks before it makes data or opens a run: :func:`lbo.train.check`,
    the data set's settings (``prepare_data``), the run's fingerprint, and every interpolation
    of the config resolved (its config.yaml and MLflow params)."""
    from lbo.learn import noise_run, slip_run
    from lbo.logs.sets import is_logs
    from lbo.sim.datasets import spec_from_cfg
    from lbo.train import check, config_hash

    if cfg.model.name == noise_run.NAME:  # lbo.train's own branch: seven noises, no net
        noise_run.check(cfg)
        OmegaConf.to_container(cfg, resolve=True)
        return
    if cfg.model.name in SLIP_MODELS:  # its own branch too: the real run, the lateral net
        slip_run.check(cfg)
        config_hash(cfg)
        OmegaConf.to_container(cfg, resolve=True)
        return
    check(cfg)
    if not is_logs(cfg):
        spec_from_cfg(cfg)
        config_hash(cfg)
    OmegaConf.to_container(cfg, resolve=True)


def data_checks(cfg) -> None:
    """``lbo.datagen``: the data set's settings (or the logs named)."""
    from lbo.logs import sets as logs
    from lbo.sim.datasets import spec_from_cfg

    if logs.is_logs(cfg):
        logs.spec_from_cfg(cfg)
    else:
        spec_from_cfg(cfg)


def evaluate_checks(cfg) -> None:
    """``lbo.evaluate``: the observers, the reference, the forms and flags, the vehicle, noise
    car and sensors, and the test grid's settings (or the test logs named)."""
    from lbo import evaluate
    from lbo.logs import sets as logs
    from lbo.scoring import grid
    from lbo.sim.datasets import spec_from_cfg
    from lbo.sim.truth import of_config
    from lbo.sim.vehicle import Vehicle

    grid.check_observers(list(cfg.observers))
    assert cfg.metric.reference in grid.REFERENCES
    evaluate._extras(cfg)
    if logs.is_logs(cfg):
        logs.spec_from_cfg(cfg, need=("test",))
    else:
        of_config(cfg, Vehicle.from_cfg(cfg.vehicle).wheelbase)
        spec_from_cfg(cfg)


def simulate_checks(cfg) -> None:
    """``lbo.simulate``: the data, noise, vehicle, car and sensors groups, as ``simulate``
    checks them before it drives anything."""
    from lbo.simulate import check

    check(cfg)


def observe_checks(cfg) -> None:
    """``lbo.observe``: the settings it checks before it reads a log or a checkpoint."""
    from lbo.logs.units import check_max_gap
    from lbo.sim.noise import Noise, check_alpha
    from lbo.sim.vehicle import Vehicle

    Noise.from_cfg(cfg.noise)
    Vehicle.from_cfg(cfg.vehicle)
    check_alpha(cfg.alpha)
    check_max_gap(cfg.max_gap)


CHECKS = {"datagen": data_checks, "evaluate": evaluate_checks, "simulate": simulate_checks,
          "observe": observe_checks, "export": lambda cfg: None}


def command_refusal(primary: str, group: str, option: str) -> Refusal | None:
    if group == "data" and option == "logs":
        return {"datagen": NEEDS_LOGS, "evaluate": NEEDS_TEST_LOGS,
                "simulate": NOT_SIMULATED}.get(primary)
    if group == "data" and option == "hill":  # its drives are named: only simulate refuses
        return NOT_SIMULATED if primary == "simulate" else None
    if group == "data" and option in SLIP_DATA and primary in ("datagen", "evaluate",
                                                                "simulate"):
        return SIDESLIP_SLIP_ONLY
    return None


KNOWN_BROKEN: dict = {}


@pytest.fixture(scope="module", autouse=True)
def store(tmp_path_factory):
    """A folder of this module's own: the MLflow store the checks look at (none is written),
    and the runs' output_dir."""
    folder = tmp_path_factory.mktemp("config_groups")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{folder / 'mlflow.db'}")
        yield folder


# --- the tests ----------------------------------------------------------------------------------


def test_every_config_group_folder_is_chosen_by_a_primary_config():
    """A folder of conf/ that no primary config chooses from would be covered by nothing here."""
    folders = {p.name for p in CONF_DIR.iterdir() if p.is_dir() and any(p.glob("*.yaml"))}
    chosen_from = {g for primary in PRIMARIES for g in groups(primary)}
    assert folders - set(LOCAL_GROUPS) <= chosen_from
    assert {"experiment", "data", "model", "trainer"} <= set(groups("train"))
    assert len(EXPERIMENTS) > 1 and all(options(g) for g in TRAIN_GROUPS)


def train_cases() -> list:
    """``experiment=E G=O`` for each experiment (and none), group and option; where O is the
    option E picks anyway, the config is E's own, composed once as ``E-own-choices``."""
    cases = []
    for e in EXPERIMENTS:
        cases.append(pytest.param(e, None, None, id=f"{name(e)}-own-choices"))
        own = chosen(e)
        cases += [pytest.param(e, g, o, id=f"{name(e)}-{g}={o}")
                  for g in TRAIN_GROUPS for o in options(g) if o != own[g]]
    return cases


def sources(choice: dict[str, str | None], *later: tuple[str, str | None]) -> list:
    """The option files a composed training config merges, in Hydra's order."""
    return [*((g, choice[g]) for g in TRAIN_GROUPS), *later]


@pytest.mark.parametrize(("experiment", "group", "option"), train_cases())
def test_each_group_option_with_each_experiment_passes_the_train_check_or_is_refused_as_listed(
        experiment, group, option, store):
    choice = chosen(experiment, group, option)
    cfg = compose_cfg("train", [*exp(experiment), *([] if group is None else
                                                    [f"{group}={option}"]),
                                f"output_dir={store / 'out'}"])
    assert_kept(cfg, *sources(choice, ("experiment", experiment)))
    expect(lambda: train_checks(cfg), train_refusal(experiment, choice))


@pytest.mark.parametrize("experiment", ["quick", "paper"])
def test_experiment_quick_and_paper_train_on_their_own_data_and_their_studies_pass(experiment,
                                                                                     store):
    """The scales make reproduce runs: the training config and the study of each search."""
    from lbo.tune import check_tune

    cfg = compose_cfg("train", [f"experiment={experiment}", f"output_dir={store / 'out'}"])
    assert cfg.data.name == experiment
    assert (cfg.model.name, cfg.model.features) == ("cnn", "frame")
    assert_kept(cfg, *sources(chosen(experiment), ("experiment", experiment)))
    train_checks(cfg)
    for search in POSE_SEARCHES:
        study = compose_cfg("tune", [f"hparams_search={search}", f"experiment={experiment}",
                                     f"output_dir={store / 'out'}"])
        assert (study.data.name, study.model.name, study.model.window) == (experiment, search, 20)
        assert check_tune(study)


@pytest.mark.parametrize("data", ["quick", "robust"])
def test_data_quick_and_robust_compose_for_every_command_that_makes_data(data, store):
    from lbo.sim.datasets import spec_from_cfg

    for primary in ("datagen", "evaluate", "simulate", "train"):
        cfg = compose_cfg(primary, [f"data={data}"])
        assert cfg.data.name == data
        assert_kept(cfg, ("data", data))
        spec = spec_from_cfg(cfg)
        assert spec.name == data and spec.truth.default
    if data == "robust":  # its own settings over the paper's it starts from
        assert spec.train["n_traj"] == 300 and spec.train["stop_and_go"] == 0.3
        assert spec.val["run_in"] == spec.test["run_in"] == 400
    train_checks(compose_cfg("train", [f"data={data}", f"output_dir={store / 'out'}"]))


@pytest.mark.parametrize(("primary", "group", "option"), [
    pytest.param(p, g, o, id=f"{p}-{g}={o}", marks=KNOWN_BROKEN.get((p, g, o), ()))
    for p in COMMANDS for g in groups(p) for o in options(g)])
def test_each_group_option_of_each_command_passes_its_checks_or_is_refused_as_listed(
        primary, group, option):
    cfg = compose_cfg(primary, [f"{group}={option}"])
    assert_kept(cfg, (group, option))
    expect(lambda: CHECKS[primary](cfg), command_refusal(primary, group, option))


@pytest.mark.parametrize(("experiment", "search"), [
    pytest.param(e, s, id=f"{name(e)}-hparams_search={s}") for e in EXPERIMENTS
    for s in SEARCHES])
def test_each_search_with_each_experiment_passes_the_tune_check_or_is_refused_as_listed(
        experiment, search, store):
    """The search runs at its own N=20 and model, over the experiment's other settings."""
    from lbo.tune import check_tune

    cfg = compose_cfg("tune", [*exp(experiment), *([] if search is None else
                                                   [f"hparams_search={search}"]),
                               f"output_dir={store / 'out'}"])
    choice = chosen(experiment, search=search)
    assert_kept(cfg, *sources(choice, ("experiment", experiment), ("hparams_search", search)))
    refusal = train_refusal(experiment, choice, search)
    expect(lambda: check_tune(cfg), refusal or (NO_SEARCH if search is None else None))


@pytest.mark.parametrize("scale", SCALES)
def test_reproduce_checks_every_training_run_of_each_scale(scale):
    from lbo.reproduce import check_reproduce

    cfg = compose_cfg("reproduce", [f"scale={scale}", "study=all"])  # every run of each part
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):  # it composes the runs
        check_reproduce(cfg)
