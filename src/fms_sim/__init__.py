"""fms_sim: instances, the coloured-timed Petri net engine, the shop nets, schedules, replay, disruptions,
snapshots of running shops (for re-planning) and the validator."""

from .benchmarks import builtin, builtin_names
from .disruptions import Breakdown, Outage, Scenario, ScenarioError
from .formats import load_instance
from .full_shop import DECISIONS, FullShop, make_shop
from .instance import Instance, InstanceError, Operation
from .petri import Deadlock, InvalidAction, Net
from .schedule import AgvTrip, OperationRecord, Schedule, ScheduleError, ToolTrip
from .replay import PlanPolicy, ReplayError, replay
from .shop import Shop
from .shopsets import bu_shop, check_training_specs, expand_specs, heldout_shops, is_reserved
from .snapshot import Snapshot, nominal_copy, snapshot
from .validate import ScheduleInvalid, check, validate

__all__ = [
    "Instance", "InstanceError", "Operation", "builtin", "builtin_names", "load_instance",
    "Net", "Shop", "FullShop", "make_shop", "DECISIONS", "InvalidAction", "Deadlock",
    "replay", "ReplayError", "PlanPolicy", "Snapshot", "snapshot", "nominal_copy",
    "Scenario", "Breakdown", "Outage", "ScenarioError",
    "Schedule", "ScheduleError", "OperationRecord", "AgvTrip", "ToolTrip",
    "validate", "check", "ScheduleInvalid",
    "bu_shop", "expand_specs", "heldout_shops", "check_training_specs", "is_reserved",
]
__version__ = "0.1.0"


def _register() -> None:
    # cheap: only the entry-point string is registered; the env module loads on gym.make("fms/Shop-v0", ...)
    import gymnasium

    if "fms/Shop-v0" not in gymnasium.registry:
        gymnasium.register(id="fms/Shop-v0", entry_point="fms_sim.env:ShopEnv")


_register()
