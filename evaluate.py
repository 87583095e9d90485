"""Evaluate a matcher (or precomputed maps) on ordered pairs of a dataset; see configs/evaluate.yaml.

python evaluate.py model=descriptor_nn data=faust_r data.root=/path/to/FAUST_r pairs=test output_dir=OUT
python evaluate.py maps_dir=DIR data=folder data.root=DIR output_dir=OUT
"""

import hydra

from shapecorr.cli.launch import check_command_line


@hydra.main(version_base="1.3", config_path="configs", config_name="evaluate")
def main(cfg) -> None:
    """Evaluate the matcher or maps of the composed config ``cfg`` (configs/evaluate.yaml)."""
    # Imported here so that `--help` and `--cfg job` answer without loading torch.
    from shapecorr.cli.evaluate import evaluate
    from shapecorr.cli.run_log import run_log

    with run_log(cfg.output_dir, "evaluate"):  # everything printed, also in <output folder>/evaluate.log
        evaluate(cfg)


if __name__ == "__main__":
    # --help, unknown options, dataset/weights paths and thread variables, before torch loads
    check_command_line(__file__, "evaluate", __doc__)
    main()
