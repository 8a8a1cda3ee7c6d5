"""Occupancy mapping: GP regression, classic GPOM, Fast-GPOM, BCM fusion, submaps, log-odds, export."""
