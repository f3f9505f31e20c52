"""The project's own developer tooling: run from a checkout, never installed."""
