"""Calibration models, one module each: far-field, near-field polynomial, traced gains, LUT, MLP,
and the convolutional network that looks at a pixel's neighbourhood.

``MODEL_NAMES`` lists the per-pixel models in the order ``--model all`` fits them;
``NEIGHBOURHOOD_MODELS`` the network, fitted only when named (``--model conv``, or
``models=["all", "conv"]``): its fit costs tens of seconds a fold where the others take seconds.
"""

from calibration.models.base import CalibrationModel, LightFieldModel, check_light_rank, solve_normals
from calibration.models.conv import ConvModel
from calibration.models.farfield import FarFieldModel
from calibration.models.lut import LookupTable, LUTModel
from calibration.models.mlp import MLPModel
from calibration.models.nearfield import NearFieldModel
from calibration.models.traced import TracedModel

MODEL_NAMES = ("far", "near", "traced", "lut", "mlp")
NEIGHBOURHOOD_MODELS = ("conv",)

__all__ = ["CalibrationModel", "LightFieldModel", "solve_normals", "check_light_rank", "FarFieldModel",
           "NearFieldModel", "TracedModel", "LookupTable", "LUTModel", "MLPModel", "ConvModel",
           "MODEL_NAMES", "NEIGHBOURHOOD_MODELS"]
