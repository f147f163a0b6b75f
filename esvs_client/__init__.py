"""esvs_client package."""
