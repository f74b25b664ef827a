"""Joins the racing env, the collectors and the losses into training runs (see ``train.py``)."""
