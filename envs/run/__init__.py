"""run wing: the closed-loop scheduler (fly, Gymnasium, headset) and the open-loop replay (eval, failures)."""
