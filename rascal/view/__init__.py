"""``rascal view``: a bird's-eye view of the live bus (or a recording) in the browser, and Foxglove."""
