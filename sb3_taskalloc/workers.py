"""``python -m sb3_taskalloc.workers``: co-train a manager and bidding workers (see
:mod:`sb3_taskalloc.experiments.cotrain`; the workers and the market are in :mod:`sb3_taskalloc.market`)."""

from sb3_taskalloc.experiments.cotrain import main

if __name__ == "__main__":
    main()
