"""The model families, one folder each: its ModelFamily, upstream hooks, compile preparer, bench
workload and conformance cases, registered with one ``register_family(FamilySpec(...))`` call."""
