"""gym wing: Gymnasium environments, one file per task on a shared base (ids registered in viotb.envs)."""
