"""Tools that are not the product: the service load benchmark and the bad-input table."""
