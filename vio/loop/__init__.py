"""Loop closure and relocalization: keyframes, place recognition, PnP verification, 4-DOF pose graph."""
