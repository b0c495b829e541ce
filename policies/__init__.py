"""Flow-matching policies (pi0-style action experts) and the frozen instruction encoder."""

from policies.flow_matching.configuration import POLICY_SIZES, FlowMatchingConfig
from policies.flow_matching.modeling import FlowMatchingPolicy
from policies.normalization import Normalizer

__all__ = ["FlowMatchingConfig", "POLICY_SIZES", "FlowMatchingPolicy", "Normalizer"]
