"""Data generators: friction-circle training set, clothoid validation and test manoeuvres."""

from lbo.datagen.build import Spec, build, spec_from_cfg, summary
from lbo.datagen.friction import Grid, accelerations, generate_train
from lbo.datagen.manoeuvres import MANOEUVRES, validation_path

__all__ = ["MANOEUVRES", "Grid", "Spec", "accelerations", "build", "generate_train",
           "spec_from_cfg", "summary", "validation_path"]
