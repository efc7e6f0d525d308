"""The DMLO matching network (§III-C): Siamese coarse-to-fine correlation, sub-pixel loss, confidence."""

from dmlo.model.config import MatcherConfig
from dmlo.model.matcher import Features, Matcher, MatchOutput, coarse_ground_truth, matching_loss

__all__ = ["Features", "MatchOutput", "Matcher", "MatcherConfig", "coarse_ground_truth", "matching_loss"]
