"""Upstream integrations (MDM, priorMDM, MotionDiffuse): patches and launcher import hooks."""
