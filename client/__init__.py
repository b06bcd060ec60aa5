"""agilegs.client: torch-free client SDK (filled in by the service work)."""
