"""`python -m experiments.benchmark`: the command (`experiments.benchmark.main`)."""

from experiments.benchmark import main
from experiments.common import run_main

if __name__ == "__main__":
    run_main(main)
