"""Policies by name, as methods are: `policy=mlp`, `policy=pi0`, or a user's own class as
`policy=my_module:MyPolicy` or `policy=path/to/file.py:MyPolicy` (no change to this repository).
The contract a policy class meets is in `policies/base.py`."""

from __future__ import annotations

import sys

from torch import nn

from policies.flow_matching.modeling import FlowMatchingPolicy
from policies.lerobot.modeling import LeRobotPi0Policy, LeRobotPi05Policy, LeRobotSmolVLAPolicy
from policies.pi0.modeling import Pi0Policy
from policies.user_class import load_class

# The built-in policies by name: a table, so the registry imports the policies and no policy
# imports the registry. A user's policy needs no entry: `policy=file.py:Class` names it.
_REGISTRY: dict[str, type[nn.Module]] = {
    "mlp": FlowMatchingPolicy, "pi0": Pi0Policy,
    # LeRobot's own classes (policies/lerobot): a random init at policy_size, or policy_path
    "lerobot_pi0": LeRobotPi0Policy, "lerobot_pi05": LeRobotPi05Policy,
    "lerobot_smolvla": LeRobotSmolVLAPolicy}


def policy_names() -> list[str]:
    return sorted(_REGISTRY)


def get_policy(spec: str) -> type[nn.Module]:
    """A policy class from a registered name or `module.path:ClassName` / `file.py:ClassName`;
    a ValueError naming the valid ones otherwise."""
    if ":" not in spec:
        if spec not in _REGISTRY:
            raise ValueError(f"unknown policy {spec!r}; valid: {', '.join(sorted(_REGISTRY))}, "
                             f"module.path:ClassName or file.py:ClassName")
        return _REGISTRY[spec]
    cls = load_class(spec, "policy")
    if not (isinstance(cls, type) and issubclass(cls, nn.Module) and hasattr(cls, "Config")):
        raise ValueError(f"{spec!r} is not a policy: it must be a torch.nn.Module with a Config "
                         f"dataclass (see docs/adding-a-policy.md)")
    return cls


def make_config(spec: str, **fields):
    """The policy's config from the harness's fields; ValueError on a bad size or value."""
    return get_policy(spec).Config(**fields)


def policy_for_config(config) -> nn.Module:
    """A fresh policy for `config`: the class whose Config is the config's class, among the
    registered ones and the classes of the module that defines the config (a user's policy)."""
    candidates = list(_REGISTRY.values())
    module = sys.modules.get(type(config).__module__)
    candidates += [v for v in vars(module).values() if isinstance(v, type)] if module else []
    for cls in candidates:
        if getattr(cls, "Config", None) is type(config) and issubclass(cls, nn.Module):
            return cls(config)
    raise ValueError(f"no policy class has {type(config).__name__} as its Config")
