
mod pipeline;
