"""ocn_data."""
