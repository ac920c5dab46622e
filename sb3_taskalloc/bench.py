"""``python -m sb3_taskalloc.bench``: see :mod:`sb3_taskalloc.experiments.bench`."""

from sb3_taskalloc.experiments.bench import main

if __name__ == "__main__":
    main()
