"""Post-processing: depth profiles, comparison with references, segregation diagnostics."""
