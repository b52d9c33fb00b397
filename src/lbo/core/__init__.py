"""The bottom layer: errors, atomic writes, paths, the typed config checks, secrets masked,
run folders, the commands' shared Hydra shell and the figures. Imports nothing else of lbo."""

LAYERS = ("core", "sim", "logs", "filters", "models", "tracking", "tuning", "serve", "scoring",
          "learn")
"""lbo's subpackages from the bottom up: a module imports from its own layer and those below
it only; the commands (``python -m lbo.<command>``, ``lbo/<command>.py``) sit on top."""
