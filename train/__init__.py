"""Train: dataset -> Rig2Image network -> checkpoints -> the model bundle (the only thing runtime reads)."""
