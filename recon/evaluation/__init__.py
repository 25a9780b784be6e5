"""Read-only over a trained field or mesh: views (load, render, score), image metrics, mesh accuracy against a truth."""
