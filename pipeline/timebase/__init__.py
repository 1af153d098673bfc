"""Time-base stage: each capture's stamps against a regular sampling grid, and the logger clock."""
