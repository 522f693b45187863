"""`rigspace view`: a usdview-style inspector in the browser, with the runtime's frames and decisions."""
