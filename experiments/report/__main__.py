"""`python -m experiments.report`: the command (`experiments.report.main`)."""

from experiments.common import run_main
from experiments.report import main

if __name__ == "__main__":
    run_main(main)
