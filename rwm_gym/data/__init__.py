"""Datasets (HDF5) and the collectors that fill them."""
