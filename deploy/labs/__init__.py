"""The reliability labs: chaos (kill and restart the roles), the soak, the lab of network namespaces."""
