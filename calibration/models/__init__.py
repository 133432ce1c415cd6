"""Calibration models, one module each: far-field, near-field polynomial, traced gains, LUT, MLP,
and the convolutional network that looks at a pixel's neighbourhood.

``MODEL_NAMES`` lists the per-pixel models in the order ``--model all`` fits them;
``NEIGHBOURHOOD_MODELS`` the network and its fast variant on the frame shrunk by 2, fitted only
when named (``--model conv``, ``--model conv-fast``, or ``models=["all", "conv"]``): a fit costs
tens of seconds a fold where the others take seconds.
"""

from calibration.models.base import CalibrationModel, LightFieldModel, check_light_rank, solve_normals
from calibration.models.conv import ConvFastModel, ConvModel
from calibration.models.farfield import FarFieldModel
from calibration.models.lut import LookupTable, LUTModel
from calibration.models.mlp import MLPModel
from calibration.models.nearfield import NearFieldModel
from calibration.models.traced import TracedModel

MODEL_NAMES = ("far", "near", "traced", "lut", "mlp")
NEIGHBOURHOOD_MODELS = ("conv", "conv-fast")

__all__ = ["CalibrationModel", "LightFieldModel", "solve_normals", "check_light_rank", "FarFieldModel",
           "NearFieldModel", "TracedModel", "LookupTable", "LUTModel", "MLPModel", "ConvModel", "ConvFastModel",
           "MODEL_NAMES", "NEIGHBOURHOOD_MODELS"]
