"""Contact laws, one module each, registered in one table."""
