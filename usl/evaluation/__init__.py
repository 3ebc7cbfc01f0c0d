"""Scoring predictions the way the paper does (Sec. 4): per-scene metrics, baselines, summaries, tables, pictures."""
