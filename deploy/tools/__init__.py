"""Policy tools (ship, average, animate) and the generator of the option reference."""
