"""Logs: a vehicle's recordings read, checked, converted and written. A log file in lbo's
form and its checks (``io``, ``checks``, ``units``), a logger's own names and units
(``formats``), a user's logs as training, validation and test sets (``sets``), and the real
drives' importers (``hguide``, ``hill``, ``comma2k19``, with ``alignment``). Above ``sim``:
it reads the data-set schema, the vehicle and the noise presets."""
