
mod graph;
