"""Stages of the analysis: one module per stage, shared by the CLI and the pipeline runner."""
