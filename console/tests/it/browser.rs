//! The console in a real browser: headless Chromium (Debian's) driven through WebDriver by
//! Selenium's Python client.
