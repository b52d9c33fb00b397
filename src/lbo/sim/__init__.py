"""The data: the kinematic bicycle and the car that slips, the noise, the truth models, the
generators of the paper's data sets and the data-set schema (a vehicle's logs: lbo.logs)."""
