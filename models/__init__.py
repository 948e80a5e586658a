"""Neural networks: encoders, FAX attention, fusion methods, heads, registry."""
