"""A simulated survey recorded offline as the daemon would record it: ``record`` plans and runs
it, ``recorder`` feeds the real session writer, ``lidar`` streams the profiler's returns."""
