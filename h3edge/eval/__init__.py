"""Evaluation: the paper's metrics, ESLAM-style mesh culling, and evaluation of any renderer."""
