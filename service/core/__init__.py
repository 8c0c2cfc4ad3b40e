"""What the service does, below HTTP: jobs, calibrations and batches submitted, validated, listed,
cancelled and served, and the uploads received to disk."""
