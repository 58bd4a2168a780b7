"""Training runtime: run directories, seed shards, the coordinator, the local and Ray backends, evaluation."""
