"""The random decision forest: one import for training, inference and the model file.

The work is split by job: `inputs` (what the forest reads of a frame: heights above the
floor, metric offset scales, the floor gate), `features` (depth-difference probes), `tree` (flat arrays),
`train` (sampling and the entry points) with `criterion`, `splitter` and `builder` (numba
training, split as scikit-learn splits it), `predict` (numba inference) and `model_file` (the
no-pickle file format); this module gathers their public names so callers write
`from topseg.core import forest`.
"""

from topseg.core.forest.features import FeatureConfig
from topseg.core.forest.inputs import ModelInput, legacy_input, model_input
from topseg.core.forest.model_file import FORMAT_VERSION, ModelFileError, load_model, save_model
from topseg.core.forest.predict import fill_posteriors, predict_labels, predict_proba
from topseg.core.forest.train import TrainConfig, train_forest, train_tree, tree_seed
from topseg.core.forest.tree import Forest, Tree, random_tree

__all__ = [
    "FORMAT_VERSION",
    "FeatureConfig",
    "Forest",
    "ModelFileError",
    "ModelInput",
    "TrainConfig",
    "Tree",
    "fill_posteriors",
    "legacy_input",
    "load_model",
    "model_input",
    "predict_labels",
    "predict_proba",
    "random_tree",
    "save_model",
    "train_forest",
    "train_tree",
    "tree_seed",
]
