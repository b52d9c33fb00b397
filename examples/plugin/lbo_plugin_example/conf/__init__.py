"""Configs found by ``hydra.searchpath=[pkg://lbo_plugin_example.conf]``: ``model=my_gru``
and ``hparams_search=my_gru``."""
