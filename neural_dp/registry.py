"""The front door of ``neural_dp``: every simulator by name, and what other stages use of the simulators.

Other stages (``dp5k_diagnose``, ``dp5k_deblur``, the demo) import ``neural_dp`` only through this module
(``tests/test_architecture.py`` checks it); the training tools they share with ``dp5k train`` come from
``dp5k_learn``. It holds nothing of its own: each name is defined once, where its job is.

* Simulators by name (:mod:`neural_dp.simulators.catalog`): :class:`SimulatorSpec` (``--simulator``:
  ``disk | butterworth | raytrace | base | neural:CKPT | diagnosed:REPORT.json``), :func:`get_simulator`,
  :func:`default_simulators`, :func:`spec_texts`, :data:`PEERS`, :data:`SYNTAX`.
* The physical base model and its effect components, which ``dp5k diagnose`` detects, fits and writes out
  (:mod:`neural_dp.simulators.base`): :class:`BaseModel`, :class:`Component`, :data:`COMPONENTS`,
  :func:`fit_parameters`, :func:`lm_fit` with its :class:`Linearization`, :func:`residual_vector` and :func:`clustered_intervals`, :func:`field_coords`, :func:`model_to_spec`,
  :func:`model_from_spec`.
* The Neural DP Simulator, its training and its structural extension: :class:`NeuralDPSimulator`,
  :func:`train` (``dp5k train``) with its :class:`TrainConfig` and :class:`ModelConfig`, :func:`extend_multiscale`,
  :func:`finetune` (a fixed number of ``dp5k train`` steps), :data:`NEW_PARAMETER_PREFIX`.
* Synthesis from RGBD frames (``dp5k synthesize``): :func:`synthesize`, :class:`SynthConfig`,
  :data:`PAPER_F_NUMBERS`.
"""

from __future__ import annotations

from .config import TrainConfig
from .model import ModelConfig, extend_multiscale
from .simulators.base import BaseModel, Component, field_coords, fit_parameters
from .simulators.base.components import COMPONENTS, Noise, fittable_names
from .simulators.base.fit import Linearization, clustered_intervals, get_values, jacobian, lm_fit, residual_vector, set_values
from .simulators.base.spec import model_from_spec, model_to_spec
from .simulators.catalog import (DIAGNOSED_PREFIX, NEURAL_PREFIX, PEERS, SYNTAX, SimulatorSpec, default_simulators,
                                 get_simulator, spec_texts)
from .simulators.interface import DPSimulator
from .simulators.neural import NeuralDPSimulator
from .synthesize import PAPER_F_NUMBERS, SynthConfig, synthesize
from .train import NEW_PARAMETER_PREFIX, finetune, train

__all__ = [
    "BaseModel", "COMPONENTS", "Component", "DIAGNOSED_PREFIX", "DPSimulator", "ModelConfig", "NEURAL_PREFIX",
    "NEW_PARAMETER_PREFIX", "NeuralDPSimulator", "Noise", "PAPER_F_NUMBERS", "PEERS", "SYNTAX", "SimulatorSpec",
    "SynthConfig", "TrainConfig", "default_simulators", "extend_multiscale", "field_coords", "finetune", "fit_parameters",
    "fittable_names", "get_simulator", "model_from_spec", "model_to_spec", "Linearization", "clustered_intervals", "jacobian", "lm_fit", "residual_vector", "set_values", "get_values", "spec_texts",
    "synthesize", "train",
]
