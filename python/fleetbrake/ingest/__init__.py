"""Files -> warehouse: the ingestion ledger, parsing, quarantine, samples, and the braking
events detected in them."""
