"""Loop-closure detection: place descriptors and candidate search (verification lives in the pipeline)."""
