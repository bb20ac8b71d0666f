"""train.evaluation: the redirection protocol on held-out subjects, test-time fitting of new faces, the report,
the figures and FID."""
