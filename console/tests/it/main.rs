//! The console's integration tests, one test binary: the real `console` binary with the real
//! roles (coordinator, learner, a sim agent) on loopback, in a temporary data folder; its API
//! over plain HTTP, its pages in headless Chromium through WebDriver (Selenium's client).

mod api;
mod browser;
mod fleet;
mod support;
mod users;
