"""Whole archives: batch filling of recorded takes and distributed training on Dask."""
