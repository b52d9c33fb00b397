"""The data: the kinematic bicycle and the car that slips, the noise, the truth models, the
generators of the paper's data sets, the data-set schema, and logs read, checked and written."""
