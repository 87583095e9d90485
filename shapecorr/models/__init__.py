"""LightningModules (backbone + matcher + loss + logging), optimizer factories and epoch schedules."""
