"""What the streaming node needs: the sample buffer and its diagnostics."""
