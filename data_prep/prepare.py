"""Precompute the shape cache of a dataset (eigenbases, descriptors, optionally geodesics).

    python data_prep/prepare.py data=faust_r data.root=/path/to/FAUST_r geodesics=heat

Options: configs/prepare.yaml (and `--help`).
"""

import hydra

from shapecorr.cli.launch import check_command_line
from shapecorr.cli.prepare import prepare


@hydra.main(version_base="1.3", config_path="../configs", config_name="prepare")
def main(cfg) -> None:
    """Fill the shape cache of the dataset of the composed config ``cfg`` (configs/prepare.yaml)."""
    prepare(cfg)


if __name__ == "__main__":
    # --help, unknown options, dataset/weights paths and thread variables, before torch loads
    check_command_line(__file__, "prepare", __doc__)
    main()
