"""The bottom layer: errors, atomic writes, paths, the typed config checks, secrets masked,
run folders, the commands' shared Hydra shell and the figures. Imports nothing else of lbo."""
