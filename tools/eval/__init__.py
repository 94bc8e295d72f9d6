"""Reading a trained policy back over recorded episodes: loading, parsing, the parsing metrics."""
