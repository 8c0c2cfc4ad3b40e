"""Skeleton spec files shipped with acinoset (``<name>.toml``)."""
