"""The Hydra shell every entry point shares: bad input is one line on stderr, exit code 2.

Every line it prints, and every log record, has its passwords masked (:mod:`lbo.core.redact`),
Hydra's own lines included; the run folder is locked for the job (:mod:`lbo.core.runfolder`).
"""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import os
import sqlite3
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NoReturn, TextIO, cast

import hydra
from omegaconf import DictConfig

from lbo.core.errors import LboError
from lbo.core.paths import CONF_DIR, REPO_ROOT
from lbo.core.redact import scrub


def fail(err: Exception) -> NoReturn:
    print(f"error: {scrub(str(err))}", file=sys.stderr, flush=True)
    sys.exit(2)


def fail_job(err: Exception) -> NoReturn:
    """:func:`fail`, or in a job of a submitit launcher (:mod:`lbo.core.launchers`): the same
    line in the job's log, then handed back to the submitting process as the job's result
    (:class:`lbo.core.launchers.JobFailed`), which ends the sweep in that line."""
    launchers = sys.modules.get("lbo.core.launchers")
    job = getattr(launchers, "current_job", None)
    if launchers is None or job is None:
        fail(err)
    line = scrub(str(err))
    print(f"error: {line}", file=sys.stderr, flush=True)
    raise launchers.JobFailed(line, job)


def os_error(e: OSError) -> LboError:
    """An OSError (read-only folder, full disk, a folder where a file should be) as one line."""
    where = e.filename if e.filename is not None else ""
    text = str(e).strip()
    reason = e.strerror or (text.splitlines()[0] if text else type(e).__name__)
    return LboError(f"{where}: {reason}" if where else reason)


def sqlite_damage(path: Path) -> str | None:
    """Why the SQLite file ``path`` is not a database that can be read (``file is not a
    database``, ``database disk image is malformed``), or None: it reads, or is missing or
    empty (MLflow and Optuna create an empty one). Reads the schema only, so it costs
    milliseconds whatever the store's size; a lock or a busy writer is not damage."""
    try:
        if not path.is_file() or path.stat().st_size == 0:
            return None
        with contextlib.closing(sqlite3.connect(path, timeout=10)) as db:
            db.execute("SELECT count(*) FROM sqlite_master").fetchone()
    except sqlite3.OperationalError:  # locked, or cannot be opened: not the file's contents
        return None
    except sqlite3.DatabaseError as e:  # SQLITE_NOTADB, SQLITE_CORRUPT
        return str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    except OSError:
        return None
    return None


def damaged_store_message(field: str, path: Path, reason: str) -> str:
    """The one line for a damaged SQLite tracking store, with advice that works when
    followed: restore the file, or move it aside so that lbo starts a new store there."""
    return (f"{field}: the SQLite tracking store {path} is damaged ({reason}); restore it "
            f"from a backup, or move it aside (mv {path} {path}.damaged) and the next lbo "
            "command starts a new, empty store there (the runs it held are then not found)")


def _database_errors(err: BaseException) -> list[BaseException]:
    """The SQLite / SQLAlchemy database errors in ``err``'s chain (its causes and contexts),
    outermost first; SQLAlchemy's wrapper is followed to the driver's own error (``orig``)."""
    found, seen = [], set()
    stack: list[BaseException | None] = [err]
    while stack:
        e = stack.pop()
        if e is None or id(e) in seen:
            continue
        seen.add(id(e))
        if isinstance(e, sqlite3.DatabaseError) or type(e).__module__.startswith("sqlalchemy"):
            found.append(e)
        stack += [getattr(e, "orig", None), e.__cause__, e.__context__]
    return found


def store_error(err: BaseException, cfg: DictConfig | None) -> LboError | None:
    """An error from a damaged SQLite tracking store as one line naming the store and how to
    fix it; None for any other error (it stays a traceback: a bug, not bad input).

    The store is the one ``cfg`` logs to (``logger.tracking_uri``) or the one lbo reads runs
    from (``MLFLOW_TRACKING_URI``, else the repo's ``mlflow.db``); the one whose schema no
    longer reads is named. An Optuna ``optuna.db`` is opened, and its damage reported, by
    :func:`lbo.tuning.storage.open_storage`."""
    from lbo.core.paths import sqlite_path, tracking_uri

    errors = _database_errors(err)
    if not errors:
        return None
    logger = cfg.get("logger") if cfg is not None else None
    candidates = []
    if logger and logger.get("tracking_uri"):
        candidates.append((str(logger.tracking_uri), "logger.tracking_uri"))
    candidates.append((tracking_uri(), "MLFLOW_TRACKING_URI"
                       if os.environ.get("MLFLOW_TRACKING_URI") else "tracking store"))
    for uri, field in candidates:
        path = sqlite_path(uri)
        reason = sqlite_damage(path) if path is not None else None
        if reason is not None:
            if os.environ.get("MLFLOW_TRACKING_URI") == uri:
                field = "MLFLOW_TRACKING_URI"
            # a reason: there is a path
            return LboError(damaged_store_message(field, cast(Path, path), reason))
    return None


class _Scrubbed:
    """A text stream that masks passwords in what is written to it (stdout, stderr)."""

    def __init__(self, stream: TextIO) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        self._stream.write(scrub(text))
        return len(text)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


class _ScrubRecords(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        clean = scrub(message)
        if clean != message:
            record.msg, record.args = clean, None
        return True


@contextlib.contextmanager
def scrubbed_output() -> Iterator[None]:
    """Mask passwords in everything printed (stdout, stderr) for the ``with`` block."""
    out, err = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = _Scrubbed(out), _Scrubbed(err)
    try:
        yield
    finally:
        sys.stdout, sys.stderr = out, err


def scrub_logs() -> None:
    """Mask passwords in every record of the root logger's handlers (Hydra's log file too)."""
    for handler in logging.getLogger().handlers:
        if not any(isinstance(f, _ScrubRecords) for f in handler.filters):
            handler.addFilter(_ScrubRecords())


LIGHTNING_ADVERT = "\N{ELECTRIC LIGHT BULB} Tip:"
"""How Lightning's advertisements begin (a cloud logger's, at every Trainer): not lbo's
output, so :func:`quiet_lightning` drops them."""


class _NoAdverts(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not record.getMessage().startswith(LIGHTNING_ADVERT)


def quiet_lightning() -> None:
    """Lightning's INFO lines once each, without its advertisements. Lightning prints them
    through its own handler ("INFO: ...") and passes them on to the root's (Hydra's) too."""
    logging.getLogger("lightning").propagate = False
    ranked = logging.getLogger("lightning.pytorch.utilities.rank_zero")  # its rank_zero_info
    if not any(isinstance(f, _NoAdverts) for f in ranked.filters):
        ranked.addFilter(_NoAdverts())


MODEL_SHORT = ("window", "features", "normalisation")
"""The model's own settings every observer has (``model.window``, ...), which a training's command
line may spell short, as the paper's command does: ``model=cnn,lstm window=20,40,60,80``."""


def respell(overrides: list[str]) -> list[str]:
    """Training overrides as Hydra reads them: ``window=20`` (and ``features=``,
    ``normalisation=``, :data:`MODEL_SHORT`) is ``model.window=20``; the rest as given."""
    return [f"model.{arg}" if arg.partition("=")[0] in MODEL_SHORT and "=" in arg else arg
            for arg in overrides]


def entry(config_name: str, run: Callable[[DictConfig], Any],
          guard: Callable[[DictConfig], None] | None = None,
          spellings: Callable[[list[str]], None] | None = None,
          short_model_keys: bool = False) -> Callable[[], Any]:
    """A ``@hydra.main`` around ``run(cfg)`` composing ``conf/<config_name>.yaml``.

    ``run``'s return value goes back to Hydra (a sweeper's objective); an LboError or an
    OSError becomes ``error: <message>`` on stderr and exit code 2. A launcher plugin named on
    the command line that is not installed is reported the same way, before Hydra composes
    anything. The job holds its run folder's lock and writes its ``.hydra`` files, without
    passwords, before ``run`` starts; ``guard(cfg)``, if given, runs before those files are
    written, to refuse a run folder that holds another run's (raise an LboError).
    ``spellings(argv)``, if given, refuses an override spelled as an older lbo took it (raise
    an LboError naming the new spelling), before Hydra reads it. With ``short_model_keys``
    (the commands that compose a training config) ``window=`` and the other
    :data:`MODEL_SHORT` keys are read as ``model.window=`` (:func:`respell`).
    """

    @hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name=config_name)
    def main(cfg: DictConfig) -> Any:
        from hydra.core.hydra_config import HydraConfig

        from lbo.core.runfolder import claim, save_hydra_files

        scrub_logs()
        quiet_lightning()
        folder = Path(HydraConfig.get().runtime.output_dir)
        try:
            if folder.resolve() == Path.cwd().resolve():
                return run(cfg)  # observe, export: they write their outputs and nothing else
            with claim(folder, "run folder"):
                if guard is not None:
                    guard(cfg)
                save_hydra_files(cfg)
                return run(cfg)
        except LboError as e:
            fail_job(e)
        except OSError as e:
            fail_job(os_error(e))
        except Exception as e:
            # a damaged tracking store fails deep inside MLflow's SQLAlchemy store (opening
            # it, looking a run up): one line naming the store, not pages of SQL
            known = store_error(e, cfg)
            if known is None:
                raise
            fail_job(known)

    def checked() -> Any:
        if any(a in ("--help", "-h") for a in sys.argv[1:]):
            print(command_help(config_name))  # Hydra's lists every group of every command
            return 0
        with scrubbed_output():
            try:
                if not (CONF_DIR / f"{config_name}.yaml").is_file():
                    raise LboError(f"lbo's configs are neither in {REPO_ROOT / 'conf'} nor in "
                                   "the installed package: reinstall lbo (pip install <repo>), "
                                   "or set LBO_ROOT=<repo>")
                ready_launcher(launcher_from_argv(sys.argv[1:]))
                check_null_groups(sys.argv[1:])
                check_truth_split(sys.argv[1:])
                if spellings is not None:
                    spellings(sys.argv[1:])
                if short_model_keys:  # Hydra reads the overrides from sys.argv
                    sys.argv[1:] = respell(sys.argv[1:])
            except LboError as e:
                fail(e)
            return main()

    return checked


def check_null_groups(argv: list[str]) -> None:
    """Refuse ``<group>=null`` in one line (Hydra raises a traceback): a config group is left
    out with ``~<group>``."""
    for arg in argv:
        key, _, value = arg.partition("=")
        if value == "null" and key.isidentifier() and (CONF_DIR / key).is_dir():
            raise LboError(f"{arg}: {key} is a config group; leave it out with ~{key} "
                           f"(or pick one: {key}=<option>)")


def check_truth_split(argv: list[str]) -> None:
    """Refuse the ``truth`` group, split into ``car`` and ``sensors``, in one line that gives
    the new spelling: ``truth=dynamic`` is ``car=dynamic``, ``truth=dynamic_drift`` is
    ``car=dynamic sensors=drift``, and ``truth.<key>=...`` is ``sensors.<key>`` for a sensor
    error (the keys of ``conf/sensors/white.yaml``) and ``car.<key>`` for any other."""
    from omegaconf import OmegaConf

    sensor_keys = set(OmegaConf.load(CONF_DIR / "sensors" / "white.yaml"))
    for arg in argv:
        key, sep, value = arg.partition("=")
        head = key.lstrip("+~")
        path = head.split("@")[0].split(".")
        if "truth" not in path:
            continue
        at = path.index("truth")
        outer, inner = ".".join(path[:at]), path[at + 1:]
        prefix = key[:len(key) - len(head)] + (outer + "." if outer else "")
        if inner:
            group = "sensors" if inner[0] in sensor_keys else "car"
            new = f"{prefix}{group}.{'.'.join(inner)}{sep}{value}"
        elif value == "dynamic_drift":
            new = f"{prefix}car=dynamic {prefix}sensors=drift"
        else:
            new = f"{prefix}car{sep}{value}"
        raise LboError(f"{arg}: the truth group is two groups now, the car and its sensors' "
                       f"errors (conf/car, conf/sensors); write {new}")


def command_help(config_name: str) -> str:
    """``python -m lbo.<command> --help``: the groups its config composes, each with its
    options, then its config file as written (every setting with the comment that explains
    it). ``--hydra-help`` still gives Hydra's own."""
    from omegaconf import OmegaConf

    path = CONF_DIR / f"{config_name}.yaml"
    groups = {}
    config = cast(dict, OmegaConf.to_container(OmegaConf.load(path)))  # a mapping's: a dict
    for item in config.get("defaults") or []:
        if not isinstance(item, dict):  # _self_
            continue
        key, choice = next(iter(item.items()))
        group = key.removeprefix("override ").lstrip("/").split("@")[0].strip()
        if not group.startswith("hydra"):
            found = sorted(f.stem for f in (CONF_DIR / group).glob("*.yaml"))
            groups[group] = f"{group}: {', '.join(found)} (default: {choice or 'none'})"
    lines = [f"python -m lbo.{config_name} [group=option ...] [key=value ...]", "",
             "== Groups (group=option) ==", *groups.values(), "",
             f"== Settings (key=value; {path.name} as lbo ships it) ==", path.read_text()]
    return "\n".join(lines)


#: Launchers named on the command line (``hydra/launcher=<name>``) -> (plugin module, package).
LAUNCHERS = {
    "joblib": ("hydra_plugins.hydra_joblib_launcher", "hydra-joblib-launcher"),
    "submitit_local": ("hydra_plugins.hydra_submitit_launcher", "hydra-submitit-launcher"),
    "submitit_slurm": ("hydra_plugins.hydra_submitit_launcher", "hydra-submitit-launcher"),
    "ray": ("hydra_plugins.hydra_ray_launcher", "hydra-ray-launcher"),
    "rq": ("hydra_plugins.hydra_rq_launcher", "hydra-rq-launcher"),
}


def check_launcher(name: str | None, field: str = "hydra/launcher") -> None:
    """Raise one line, with the install command, if launcher ``name``'s plugin is missing.

    ``basic`` (Hydra's own, serial) and launchers not listed in :data:`LAUNCHERS` pass.
    """
    if not name or name not in LAUNCHERS:
        return
    module, package = LAUNCHERS[name]
    try:
        found = importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:
        found = False
    if not found:
        raise LboError(f"{field}={name}: the Hydra plugin {package} is not installed "
                       f"(pip install {package}, or make install, which installs lbo[launchers])")


RECLAIM_WARNING = "ignore:resource_tracker:UserWarning"
"""The warnings filter that hides loky's resource tracker's reclaims (:func:`ready_launcher`)."""


def ready_launcher(name: str | None, field: str = "hydra/launcher") -> None:
    """Check launcher ``name`` (:func:`check_launcher`) and ready it to fail in one line.

    When a job of a joblib sweep fails, joblib stops the sweep and kills the workers still
    running; loky's resource tracker (a process of its own, which outlives this one by a
    moment) then unlinks the semaphores those workers held and warns about each, after the
    job's one-line error, and only when a second job was still running (a race under load).
    The unlinking is right and is kept; its warning is filtered, through the environment the
    tracker is started with.

    submitit's launchers (``submitit_slurm``, ``submitit_local``) are run as lbo's
    (:mod:`lbo.core.launchers`), whose failed jobs end the sweep in one line too.
    """
    check_launcher(name, field)
    if name in ("submitit_slurm", "submitit_local"):
        from lbo.core.launchers import install

        install()
    if name == "joblib":
        held = os.environ.get("PYTHONWARNINGS", "")
        if RECLAIM_WARNING not in held.split(","):
            os.environ["PYTHONWARNINGS"] = ",".join(w for w in (held, RECLAIM_WARNING) if w)


def launcher_from_argv(argv: list[str]) -> str | None:
    """The launcher a Hydra command line picks (``hydra/launcher=joblib``), if any."""
    for arg in argv:
        key, _, value = arg.lstrip("+~").partition("=")
        if key == "hydra/launcher" and value:
            return value
    return None


def launcher_context(config: DictConfig) -> Any:
    """The ``hydra.types.HydraContext`` a launcher plugin is instantiated with, for the
    composed ``config`` (with its Hydra node): the global config loader and the callbacks
    ``config`` names.

    Hydra has no public constructor for its callbacks; this is the one place lbo reaches its
    private ``hydra._internal.callbacks`` (``hydra-core`` is pinned below 1.4; a move there is one
    ImportError here, which ``tests/test_scaling.py`` catches)."""
    from hydra._internal.callbacks import Callbacks
    from hydra.core.global_hydra import GlobalHydra
    from hydra.types import HydraContext

    return HydraContext(config_loader=GlobalHydra.instance().config_loader(),
                        callbacks=Callbacks(config))
