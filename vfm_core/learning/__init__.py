"""How models learn: MAP batch training and the learning methods that keep a model current.

- :mod:`vfm_core.learning.training`: :func:`fit_batch` (MAP, early stopping), the batch
  settings per model (:data:`DEFAULT_TRAIN`, from each model's ``train_defaults``).
- :mod:`vfm_core.learning.method`: the learning-method protocol (:class:`LearningMethod`),
  the registry (:data:`METHODS`) and :func:`parse_method`.
- One module per method: :mod:`~vfm_core.learning.online` (``ol``),
  :mod:`~vfm_core.learning.periodic` (``pbl:<period>``),
  :mod:`~vfm_core.learning.triggered` (``pbl:auto``), :mod:`~vfm_core.learning.bayes`
  (``bayes``: a Kalman filter with drift and predictive intervals).
- :mod:`vfm_core.learning.memory`: the measurements a retrain reads.
- :mod:`vfm_core.learning.stacking`: many one-well models run as one multi-well model
  (what the methods' group operations use).
- The learners that run a model and a method over time, sample by sample:
  :mod:`vfm_core.learning.streaming` (``WellLearner``, one well: the service's learner;
  ``predict_many``/``learn_many`` over many wells; the ``Learner`` protocol) and
  :mod:`vfm_core.learning.field` (``FieldLearner``: the field-wide ``mtl``, a ``FieldWell``
  facade per well). They import this package, never the reverse: importing
  ``vfm_core.learning`` does not load them.
"""

from vfm_core.learning.bayes import BayesianFilter
from vfm_core.learning.memory import FrameMemory, Memory, WellMemory
from vfm_core.learning.method import (
    METHODS,
    NEVER,
    Forecast,
    LearningMethod,
    parse_method,
    register,
)
from vfm_core.learning.online import DEFAULT_ONLINE, OnlineLearning, OnlineSettings
from vfm_core.learning.periodic import PeriodicBatch
from vfm_core.learning.training import (
    DEFAULT_TRAIN,
    TrainSettings,
    fit_batch,
    settings_from_dict,
)
from vfm_core.learning.triggered import DriftTriggered

__all__ = [
    "METHODS",
    "NEVER",
    "BayesianFilter",
    "DEFAULT_ONLINE",
    "DEFAULT_TRAIN",
    "DriftTriggered",
    "Forecast",
    "FrameMemory",
    "LearningMethod",
    "Memory",
    "OnlineLearning",
    "OnlineSettings",
    "PeriodicBatch",
    "TrainSettings",
    "WellMemory",
    "fit_batch",
    "parse_method",
    "register",
    "settings_from_dict",
]
