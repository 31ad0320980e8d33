import pytest

from fms_sim import Instance
from fms_sim.shop import Shop


def run_first(inst: Instance, prefer=None):
    """Run the shop always taking the lowest enabled action (or the first in ``prefer`` that is legal)."""
    shop = Shop(inst)
    while not shop.done:
        legal = shop.legal_actions()
        pick = next((a for a in (prefer or []) if a in legal), legal[0])
        shop.act(pick)
    return shop.schedule()


@pytest.fixture
def first():
    return run_first
