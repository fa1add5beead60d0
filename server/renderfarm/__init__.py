"""Progressive Monte Carlo render farm."""
