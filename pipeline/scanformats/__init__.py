"""Readers of real RGB-D scan layouts, one module per layout (see :mod:`pipeline.scanformats.detect`)."""
