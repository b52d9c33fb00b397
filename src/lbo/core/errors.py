"""The one exception type that entry points turn into a one-line message."""


class LboError(ValueError):
    """Bad input (config, data file, checkpoint); the message names the field and its form."""


class TrainingDiverged(LboError):
    """The loss became NaN or inf: the weights are lost, no checkpoint of them is kept."""


def located(source: str | None, text: str) -> str:
    """``text`` prefixed with where it was found (``"input log.csv: ..."``), if anywhere."""
    return f"{source}: {text}" if source else text
