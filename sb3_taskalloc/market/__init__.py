"""Worker entities that bid their wage (SB3's DDPG) and the market that runs them around a ``bidding=True`` env."""

from sb3_taskalloc.market.market import BiddingEnv, WorkerMarket, bidding_env, load_worker_config, make_market
from sb3_taskalloc.market.workers import BiddingWorkers, worker_observations

__all__ = [
    "BiddingEnv",
    "BiddingWorkers",
    "WorkerMarket",
    "bidding_env",
    "load_worker_config",
    "make_market",
    "worker_observations",
]
