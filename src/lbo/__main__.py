"""``lbo <command> [overrides ...]``: the console script, the same as
``python -m lbo.<command> [overrides ...]`` (which stays, since users type it).

    lbo train -m model=cnn,lstm window=20,40,60,80
    lbo observe observer=ekf input=log.csv output=estimates.csv
    lbo --help        # the commands; lbo <command> --help: that command's settings
"""

from __future__ import annotations

import importlib
import sys

COMMANDS = {
    "datagen": "generate the paper's data sets (the cache)",
    "simulate": "simulate one log (or a fleet) of a manoeuvre",
    "train": "train an observer (Hydra sweeps with -m)",
    "tune": "an Optuna study of an observer's hyperparameters",
    "evaluate": "score a trained observer and the classical peers on a test set",
    "observe": "run an observer on a log",
    "export": "export a trained observer (TorchScript, ONNX) or register it in MLflow",
    "reproduce": "the paper's study end to end: tables and figures",
    "ablation": "the paper's crossover, variant by variant",
    "realdrive": "the onavdata hill drive end to end",
    "receiver_study": "simulated single-antenna logs: every observer beside an oracle",
}
"""The commands, each a module ``lbo.<command>`` with a ``main``."""


def usage() -> str:
    width = max(map(len, COMMANDS))
    lines = ["usage: lbo <command> [overrides ...]   (= python -m lbo.<command> ...)", "",
             "commands:"]
    lines += [f"  {name:<{width}}  {what}" for name, what in COMMANDS.items()]
    lines += ["", "lbo <command> --help lists that command's settings."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run ``lbo.<argv[0]>``'s command with the rest of ``argv`` (default: sys.argv[1:])."""
    args = sys.argv[1:] if argv is None else list(argv)
    if not args or args[0] in ("-h", "--help"):
        print(usage())
        return 0
    name, rest = args[0], args[1:]
    if name not in COMMANDS:
        print(f"error: unknown command {name!r}; expected one of {', '.join(COMMANDS)} "
              "(lbo --help)", file=sys.stderr)
        return 2
    command = importlib.import_module(f"lbo.{name}")
    sys.argv = [f"lbo {name}", *rest]  # Hydra reads the overrides from sys.argv
    result = command.main()
    return result if isinstance(result, int) else 0


if __name__ == "__main__":
    sys.exit(main())
