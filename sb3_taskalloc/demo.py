"""``python -m sb3_taskalloc.demo``: see :mod:`sb3_taskalloc.experiments.demo`."""

from sb3_taskalloc.experiments.demo import main

if __name__ == "__main__":
    main()
