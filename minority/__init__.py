"""The `minority` command and the all-in-one demo; the work lives in the other packages."""
