"""LeRobot's own policies (PI0, PI0.5, SmolVLA) as Retain policies: `policy=lerobot_pi0`,
`lerobot_pi05`, `lerobot_smolvla`, with `policy_path=` for a checkpoint (docs/lerobot.md)."""

from policies.lerobot.configuration import (
    LeRobotConfig,
    LeRobotPi0Config,
    LeRobotPi05Config,
    LeRobotSmolVLAConfig,
)
from policies.lerobot.modeling import (
    LeRobotPi0Policy,
    LeRobotPi05Policy,
    LeRobotPolicy,
    LeRobotSmolVLAPolicy,
)

__all__ = ["LeRobotConfig", "LeRobotPi0Config", "LeRobotPi05Config", "LeRobotSmolVLAConfig",
           "LeRobotPolicy", "LeRobotPi0Policy", "LeRobotPi05Policy", "LeRobotSmolVLAPolicy"]
