"""Command-line entry points behind train.py, evaluate.py and data_prep/prepare.py."""
