"""A small user-side package of scripted experts (see :mod:`mypkg.experts`)."""

from mypkg.experts import lunar_lander, lunar_lander_continuous, mountain_car, reacher

__all__ = ["lunar_lander", "lunar_lander_continuous", "mountain_car", "reacher"]
