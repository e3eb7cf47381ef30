"""scenarios wing: the one scenario registry, the motion library, and the failure catalog."""
