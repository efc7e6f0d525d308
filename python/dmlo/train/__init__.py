"""Training of the matcher: pair dataset, trainer with checkpoint/resume, DDP via `torchrun -m dmlo.train`."""

from dmlo.train.config import TrainConfig
from dmlo.train.dataset import ArrayPairDataset, Augmentation, PairDataset, RustGeometry, pair_indices
from dmlo.train.trainer import Trainer, load_model

__all__ = [
    "ArrayPairDataset",
    "Augmentation",
    "PairDataset",
    "RustGeometry",
    "TrainConfig",
    "Trainer",
    "load_model",
    "pair_indices",
]
