"""Adapters that put existing models and diffusions into sparse keyframe mode."""
