"""Data in and out of the model: readers of recorded data sets (:mod:`~hippomap.io.datasets`: hippomap
folders, TUM RGB-D, g2o graphs, ground-truth files; :mod:`~hippomap.io.rosbag`: ROS 1 / ROS 2 bags) and
writers of a map and of a session (:mod:`~hippomap.io.exports`: TUM, g2o, JSON, map plot;
:mod:`~hippomap.io.session_export`: a session's inputs as a data folder or a ROS 2 bag).

The model never imports this package. Bags need the ``rosbag`` extra (``pip install 'hippomap[rosbag]'``),
TUM files and the map plot the ``eval`` extra; the other readers and writers need only the core install.
"""
