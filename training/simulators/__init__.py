"""Simulators of the paper's systems (Bouc-Wen benchmark, BERT stand-in)."""
