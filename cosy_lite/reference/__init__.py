"""Reference models shipped with the package (:mod:`cosy_lite.reference.catalog`)."""
