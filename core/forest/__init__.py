"""The random decision forest: one import for training, inference and the model file.

The work is split by job: `tree` (flat arrays), `forest_train` (numba training),
`forest_predict` (numba inference) and `model_file` (the no-pickle file format); this
module gathers their public names so callers write `from topseg.core import forest`.
"""

from topseg.core.forest.features import FeatureConfig
from topseg.core.forest.model_file import FORMAT_VERSION, ModelFileError, load_model, save_model
from topseg.core.forest.predict import labels_from_proba, predict_labels, predict_proba
from topseg.core.forest.train import TrainConfig, train_forest, train_tree, tree_seed
from topseg.core.forest.tree import Forest, Tree, random_tree

__all__ = [
    "FORMAT_VERSION",
    "FeatureConfig",
    "Forest",
    "ModelFileError",
    "TrainConfig",
    "Tree",
    "labels_from_proba",
    "load_model",
    "predict_labels",
    "predict_proba",
    "random_tree",
    "save_model",
    "train_forest",
    "train_tree",
    "tree_seed",
]
