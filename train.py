"""Train a learned correspondence model (default: Deep Shells on the embedded synthetic data); see configs/train.yaml.

python train.py
python train.py experiment=deep_shells_faust_r data.root=/path/to/FAUST_r trainer=gpu
python train.py ckpt_path=outputs/train/<run>/checkpoints/last.ckpt
"""

import hydra

from shapecorr.cli.launch import check_command_line


@hydra.main(version_base="1.3", config_path="configs", config_name="train")
def main(cfg) -> None:
    """Train the model of the composed config ``cfg`` (configs/train.yaml)."""
    # Imported here so that `--help` and `--cfg job` answer without loading torch.
    from shapecorr.cli.train import train
    from shapecorr.cli.run_log import run_log

    with run_log(cfg.paths.output_dir, "train"):  # everything printed, also in <output folder>/train.log
        train(cfg)


if __name__ == "__main__":
    # --help, unknown options, dataset/weights paths and thread variables, before torch loads
    check_command_line(__file__, "train", __doc__)
    main()
