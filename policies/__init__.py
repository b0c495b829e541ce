"""Flow-matching policies (pi0-style action experts), their registry, and the frozen
instruction encoder. The policy contract is in `policies/base.py`."""

from policies.base import FlowMatchingBase, PolicyConfig
from policies.flow_matching.configuration import POLICY_SIZES, FlowMatchingConfig
from policies.flow_matching.modeling import FlowMatchingPolicy
from policies.normalization import Normalizer
from policies.pi0.configuration import Pi0Config
from policies.pi0.modeling import Pi0Policy
from policies.registry import (
    get_policy,
    make_config,
    policy_for_config,
    policy_names,
)

__all__ = ["FlowMatchingBase", "PolicyConfig", "FlowMatchingConfig", "POLICY_SIZES",
           "FlowMatchingPolicy", "Normalizer", "Pi0Config", "Pi0Policy", "get_policy",
           "make_config", "policy_for_config", "policy_names"]
