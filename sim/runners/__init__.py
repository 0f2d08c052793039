"""Backend-agnostic runners: the same stimulus in, one result out."""
