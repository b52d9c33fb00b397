"""An example plug-in for lbo: a GRU observer over the window, and its configs."""
