"""What every layer uses: refusing impossible input and warning on implausible input (checks)."""
