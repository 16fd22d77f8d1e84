"""Tests of physics."""
